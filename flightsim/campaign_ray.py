"""Campaign runs as Ray tasks (``flightsim campaign … --backend ray [--address ADDR]``).

A Ray cluster shares no file system with the driver, so a run travels as data both ways:

* :func:`pack_inputs` reads the scenario TOML, the world it names and the companion configuration
  into a dict of file texts (the scenario's ``world`` and ``companion_config`` rewritten to the
  packed names);
* :func:`run_shipped` (the task, on any node with this package installed: ``pip install
  '.[ray]'``) writes them into a private temporary directory, runs the job there with
  :func:`flightsim.campaign.run_one` and returns the result with the run's output files as bytes
  (the video only with ``--keep-video``);
* :func:`run_jobs` submits every job, collects the results as they finish and writes each run's
  files into the campaign's ``runs/seed_NNNN/`` on the driver, so the report and pooling are the
  same as with the local process pool (the default).

Ray is an optional extra; without it ``--backend ray`` is a :class:`ConfigError` saying how to
install it.
"""

from __future__ import annotations

import dataclasses
import shutil
import tempfile
from pathlib import Path
from typing import Callable

from companion.errors import ConfigError

#: run outputs larger than this are not shipped back (a video without --keep-video is deleted anyway)
MAX_RETURN_BYTES = 200 * 1024 * 1024


def require_ray():
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ConfigError("--backend ray needs Ray: pip install '.[ray]' (or pip install 'ray>=2.9'); "
                          "the default --backend process needs nothing more") from None
    import ray

    return ray


def pack_inputs(scenario: Path, companion_config: Path | None) -> dict[str, str]:
    """The texts a run needs, keyed by the names they get on the worker (module docstring)."""
    from flightsim.scenario import set_path_key

    scenario = Path(scenario)
    text, world = set_path_key(scenario.read_text(encoding="utf-8"), "world", "world.toml")
    if world is None:
        raise ConfigError(f"{scenario}: no [scenario] world = \"…\" line to ship")
    files = {"world.toml": (scenario.parent / world).read_text(encoding="utf-8")}
    text, _ = set_path_key(text, "companion_config", "")  # the run gets the resolved config below
    files["scenario.toml"] = text
    if companion_config is not None:
        files["companion.toml"] = Path(companion_config).read_text(encoding="utf-8")
    return files


def run_shipped(job, files: dict[str, str], run_fn: Callable | None = None) -> dict:
    """The Ray task: run ``job`` in a private directory from the shipped ``files``; returns its result
    (:func:`flightsim.campaign.run_one`) with ``files_out`` = {name: bytes} of the run directory."""
    from flightsim.campaign import run_one

    run_fn = run_fn or run_one
    with tempfile.TemporaryDirectory(prefix="flightsim_ray_") as tmp:
        tmp = Path(tmp)
        for name, text in files.items():
            (tmp / name).write_text(text, encoding="utf-8")
        local = dataclasses.replace(job, scenario=str(tmp / "scenario.toml"), run_dir=str(tmp / "run"),
                                    companion_config=str(tmp / "companion.toml") if "companion.toml" in files else None)
        res = run_fn(local)
        out: dict[str, bytes] = {}
        run_dir = Path(local.run_dir)
        if run_dir.is_dir():
            for p in sorted(run_dir.iterdir()):
                if p.is_file() and p.stat().st_size <= MAX_RETURN_BYTES:
                    out[p.name] = p.read_bytes()
        res = dict(res, dir=job.run_dir, files_out=out)
        if res.get("score"):  # paths inside the score point at the worker's temporary directory: name the driver's
            inputs = res["score"].get("inputs") or {}
            for k, v in list(inputs.items()):
                inputs[k] = str(Path(job.run_dir) / Path(v).name)
        return res


def run_jobs(jobs: list, scenario: Path, companion_config: Path | None, address: str | None,
             on_result: Callable[[object, dict], None], run_fn: Callable | None = None) -> None:
    """Run ``jobs`` as Ray tasks (connecting to ``address``, or a local Ray when None) and hand each
    result to ``on_result(job, result)`` as it finishes, after writing its files into ``job.run_dir``."""
    ray = require_ray()
    files = pack_inputs(scenario, companion_config)
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, ignore_reinit_error=True, log_to_driver=False, include_dashboard=False)
    try:
        task = ray.remote(num_cpus=1)(run_shipped)
        files_ref = ray.put(files)
        pending = {task.remote(job, files_ref, run_fn): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                job = pending.pop(ref)
                try:
                    res = ray.get(ref)
                except Exception as exc:  # the task or its node died: recorded like a failed run
                    res = {"seed": job.seed, "dir": job.run_dir, "status": "failed",
                           "error": f"{type(exc).__name__}: {exc}", "wall_s": None, "score": None, "files_out": {}}
                run_dir = Path(job.run_dir)
                if run_dir.exists():
                    shutil.rmtree(run_dir)
                run_dir.mkdir(parents=True)
                for name, data in (res.pop("files_out", None) or {}).items():
                    (run_dir / name).write_bytes(data)
                if res.get("score") and (run_dir / "score.json").is_file():  # name the driver's files, not the task's
                    from flightsim.score.files import write_score

                    write_score(run_dir, res["score"])
                on_result(job, res)
    finally:
        if started_here:
            ray.shutdown()


__all__ = ["pack_inputs", "run_shipped", "run_jobs", "require_ray", "MAX_RETURN_BYTES"]
