"""bench.compute's --config: the report names the configuration measured; a missing file is a usage error."""

import subprocess
import sys
from pathlib import Path

from bench import compute

ROOT = Path(__file__).resolve().parents[1]


def _res(config):
    row = {"case": "synthetic", "kernels": "numba", "frames": 10, "mean_tracks": 270.0, "mean_converged": 200.0,
           "cpu_mean_ms": 6.0, "cpu_p50_ms": 5.0, "cpu_p99_ms": 9.0, "stage_cpu_ms": {"track": 4.0, "estimate": 1.0}}
    return {"rows": [row], "target_ms": compute.TARGET_MS, "config": config, "numba": "0", "machine": "x", "python": "3"}


def test_report_names_the_configuration_and_its_command():
    shipped = compute.markdown(_res(None))
    assert "shipped configuration" in shipped and "`python -m bench compute --write docs/BENCHMARKS.md`" in shipped
    other = compute.markdown(_res("configs/companion_refine.toml"))
    assert "configuration `configs/companion_refine.toml`" in other
    assert "`python -m bench compute --config configs/companion_refine.toml`" in other and "shipped" not in other


def test_missing_config_is_a_usage_error():
    r = subprocess.run([sys.executable, "-m", "bench.compute", "--config", "no/such.toml"], capture_output=True, text=True,
                       cwd=ROOT)
    assert r.returncode == 2 and "--config" in r.stderr


def test_the_opt_in_refinement_configuration_loads_with_it_on():
    from companion.io.config_files import load_companion_config

    cfg = load_companion_config(ROOT / "configs" / "companion_refine.toml")
    assert cfg.ekf_anchored.refine and cfg.ekf_anchored.refine_max_obs == 128
    assert not load_companion_config(None).ekf_anchored.refine
