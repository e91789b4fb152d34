"""``companion monitor CONN``: a ground-station view of a running companion in the terminal.

What the messages mean is in docs/derivations/sectors.md; this package only listens and shows.
Four layers, each importing only the ones before it:

:mod:`.decode` (pure)
    :func:`~.decode.decode_obstacle_distance` / :func:`~.decode.decode_distance_sensor` read one
    message the way the MAVLink spec defines it (UINT16_MAX = unknown, ``max_distance + 1`` =
    clear, ``increment_f`` used when non-zero, else ``increment``; ``angle_offset``; ``frame``:
    BODY_FRD = forward-aligned, GLOBAL / LOCAL_NED = north-aligned; DISTANCE_SENSOR ``covariance``
    in cm², 255 = unknown); :func:`~.decode.bin_sectors` folds the sectors into display bins.
:mod:`.state` (pure; the caller's clock)
    :class:`~.state.MonitorState` folds decoded pymavlink messages from the companion into the
    latest sectors, forward range, HEARTBEAT, diagnostics, STATUSTEXTs, rates, counts and wire
    errors; :meth:`~.state.MonitorState.snapshot` turns it into an immutable
    :class:`~.state.Snapshot` with ages, stale flags and the link state
    (:meth:`~.state.Snapshot.to_json` for ``--json``).
:mod:`.view` (pure)
    :func:`~.view.render` draws a snapshot as a rich renderable (a 72-sector strip; stale data
    grey and labelled STALE, never as current); :func:`~.view.render_text` as plain text.
:mod:`.runner` (I/O, thin)
    :func:`~.runner.open_connection`, :class:`~.runner.Reader` (non-blocking reads, parser errors
    counted, never raised), :func:`~.runner.run_monitor` (the loop: rich ``Live`` view, text or JSON
    snapshots, the GCS HEARTBEAT) and :func:`~.runner.cmd_monitor` (``companion monitor``).
"""
