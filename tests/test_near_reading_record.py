"""A camera's near reading in a recording (service/mcap_record.py, mcap_replay.py, inspect_cmd.py):
``near_reading`` and ``depth_step_inv`` are recorded with the camera's model, the replay's cameras
have them, and ``pointfence inspect`` names them (S8: a replay reproduces the run)."""
from __future__ import annotations

from test_mcap_record import _assert_exact_up_to_dropped_snapshots, _finish, _serve, _stop

from pointfence.service.mcap_read import open_recording
from pointfence.service.mcap_replay import replay


def test_a_run_with_near_reading_replays_with_it(tmp_path):
    """A camera whose readings are taken at the near end of their steps (``near_reading``, a
    disparity step) is recorded with both settings, and the replay's cameras have them: the run
    replays exactly (without them the replay's fixture would sit half a step further back)."""
    from pointfence.bench.e2e import LIGHT_SCENE
    from pointfence.service.mcap_replay import recording_config

    assert LIGHT_SCENE.count("[[camera]]") == 1
    scene = LIGHT_SCENE.replace("[[camera]]\n", "[[camera]]\nnear_reading = true\ndepth_step_inv = 0.0029\n")
    rec = tmp_path / "near.mcap"
    serve, dev = _serve(tmp_path, rec, 3.0, scene_text=scene)
    try:
        _finish(serve, dev)
    finally:
        _stop(serve, dev)
    r = open_recording(rec)
    cam = r.meta["cameras"][0]
    assert cam["near_reading"] is True and cam["depth_step_inv"] == 0.0029
    replayed = recording_config(r).cameras[0].camera
    assert replayed.near_reading and replayed.depth_step_inv == 0.0029
    from pointfence.service import inspect_cmd

    report, _ = inspect_cmd.build(rec, measure=False)
    assert "readings at the near end of their steps, disparity step 0.0029 1/m" in inspect_cmd.text(report)
    _, check = replay(r)
    _assert_exact_up_to_dropped_snapshots(r, check)
