"""mrskin.bridge: statistics equal to the C++ run's, the callback, streams, Ctrl-C, errors."""
import json
import os
import signal
import socket
import struct
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


def crc32c(data):
    """CRC-32C written from docs/sources.md, not from the library's code."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def udp_sample(seq, stamp_ns):
    """A lifted sample (no force, no depth) as docs/sources.md's version-1 datagram."""
    body = struct.pack("<4sHHIIqddddd", b"MRSS", 1, 0, seq, 0, stamp_ns, 0.0, 0.0, 0.0, 0.0, 0.003)
    return body + struct.pack("<I", crc32c(body))


def test_the_mock_finger_waits_for_a_streams_first_sample():
    assert crc32c(b"123456789") == 0xE3069283
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    running = threading.Event()  # the first tick reached the callback
    sending = threading.Event()
    samples = []
    stream_t_s = []  # the tick time at which the callback first saw the robot sending

    def on_tick(tick):
        samples.append(tick)
        running.set()
        if sending.is_set() and not stream_t_s:
            stream_t_s.append(tick.t_s)

    def robot():  # starts late, as a DDS follower does after discovery; bounded, loopback only
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
            running.wait(5.0)
            threading.Event().wait(0.4)
            sending.set()
            for k in range(1200):
                out.sendto(udp_sample(k, k * 1000000), ("127.0.0.1", port))
                threading.Event().wait(0.001)

    sender = threading.Thread(target=robot)
    sender.start()
    try:
        stats = bridge.run_realtime(f"udp://127.0.0.1:{port}", "mock://?seed=5&finger=demo", duration_s=1.6,
                                    callback=on_tick, decimation=5)
    finally:
        sender.join()
    assert stats["samples_accepted"] > 0 and stream_t_s
    # The callback drains every 10 ms (later on a loaded machine): the robot began at most then.
    start = stream_t_s[0]
    before = [float(np.max(s.true_force_N)) for s in samples if 0.05 < s.t_s < start - 0.15]
    after = [float(np.max(s.true_force_N)) for s in samples if s.t_s > start + 0.5]
    assert len(before) > 20 and after
    # Until the stream the finger rests at the demo's start (on the skin at depth 0, where the
    # reservoir's precharge alone pushes it); from the stream's first sample it presses 0 -> 4 mm
    # in 1 s. A finger that did not wait pressed from the run's start (0.19 -> 0.34 N by 0.4 s).
    assert max(before) - min(before) < 0.01 and max(before) < 0.25, (min(before), max(before))
    assert max(after) > 0.45, max(after)


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
