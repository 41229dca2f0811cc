"""mrskin.bridge: statistics equal to the C++ run's, the callback, streams, Ctrl-C, errors."""
import json
import os
import signal
import subprocess
import threading

import numpy as np
import pytest

import mrskin
from mrskin import bridge


def cpp_stats(scene, seconds, uri):
    """The same scene through the C++ tests' rig (tests/bridge/scene_rig.hpp), as JSON."""
    out = subprocess.run([os.environ["MRSKIN_SCENE_STATS"], scene, str(seconds), uri],
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out)


@pytest.mark.parametrize("scene", ["hand", "tumour"])
def test_closed_loop_statistics_equal_the_cpp_run(scene):
    uri = "mock://?seed=7"
    expected = cpp_stats(scene, 3.0, uri)
    got = bridge.run_simulated(scene, uri, duration_s=3.0)
    assert got == expected
    assert got["ticks"] == 3000 and got["force_samples"] > 0


def test_callback_gets_decimated_ticks_and_leaves_the_statistics_alone():
    samples = []
    stats = bridge.run_simulated("demo", "mock://?seed=2", duration_s=1.0, callback=samples.append, decimation=10)
    plain = bridge.run_simulated("demo", "mock://?seed=2", duration_s=1.0)
    assert (stats.pop("callback_samples"), stats.pop("callback_dropped")) == (100, 0)
    assert stats == plain
    assert len(samples) == 100
    times = [s.t_s for s in samples]
    assert times == sorted(times) and times[1] - times[0] == pytest.approx(0.010)
    last = samples[-1]
    assert last.target_N.shape == last.observed_force_N.shape == last.true_force_N.shape == (13,)
    assert max(float(np.max(s.true_force_N)) for s in samples) > 0.1  # the finger pressed


def test_a_recorded_stream_on_the_simulated_clock(tmp_path):
    path = tmp_path / "press.stream"
    lines = ["# mrskin-stream 1"]
    for k in range(1500):
        depth = 4e-3 * min(1.0, k / 500.0)
        lines.append(f"{k * 1000000} {k * 1000000} {300.0 * depth} {depth} 0 0 0.003")
    path.write_text("\n".join(lines) + "\n")
    stats = bridge.run_simulated(f"replay://{path}", "mock://?seed=4&finger=demo", duration_s=1.5)
    assert stats["slave_samples"] > 1000
    assert stats["force_samples"] > 0
    # the stream's own counters, as mrskin-bridged reports them
    assert stats["samples_accepted"] > 1000 and stats["samples_dropped"] == 0


def test_realtime_run_with_a_callback():
    samples = []
    stats = bridge.run_realtime("demo", "mock://?seed=5", duration_s=0.5, callback=samples.append, decimation=20)
    assert stats["ticks"] > 0 and stats["callback_samples"] > 0
    assert len(samples) == stats["callback_samples"]
    assert samples[0].true_force_N is not None


def test_ctrl_c_stops_a_realtime_run_cleanly():
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        bridge.run_realtime("demo", "mock://", duration_s=0)  # until Ctrl-C
    timer.join()
    # The unit was released: it opens again.
    assert bridge.run_realtime("demo", "mock://", duration_s=0.05)["ticks"] >= 0


def test_bad_sources_and_devices_raise_the_documented_errors():
    with pytest.raises(mrskin.InvalidArgument):
        bridge.run_simulated("no-such-scene")
    with pytest.raises(mrskin.InvalidArgument):
        bridge.run_simulated("bogus://x")
    with pytest.raises(mrskin.InvalidArgument):
        bridge.run_simulated("demo", "hid://1209:4d52")
    with pytest.raises(mrskin.InvalidArgument):
        bridge.run_simulated("demo", duration_s=float("nan"))
    with pytest.raises(mrskin.ProfileNotFound):
        bridge.run_simulated("demo", "mock://no-such-profile")
    with pytest.raises(mrskin.InvalidArgument):
        bridge.run_simulated("demo", callback=42)
    assert "hand" in bridge.scene_names()
