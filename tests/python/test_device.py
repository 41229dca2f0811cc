"""mrskin.device on the mock: identity, telemetry, states, currents, calibration, and errors."""
import math

import numpy as np
import pytest

import mrskin


def test_identity_telemetry_states_and_currents():
    with mrskin.open_device("mock://?seed=3") as dev:
        info = dev.info
        assert (info["rows"], info["cols"], info["valves"]) == (5, 5, 12)
        assert dev.is_mock
        assert dev.profile.name == "mr-skin-5x5"
        assert dev.state == "disabled"
        dev.enable()
        assert dev.state == "enabled"
        dev.press_finger(2.0, 2.0, 3e-3)
        currents = np.full(info["valves"], 0.5 * info["max_current_A"])
        dev.set_valve_currents(currents)
        t_us, readings = dev.wait_telemetry()
        assert readings.shape == (info["sensors"],)
        t2_us, _ = dev.wait_telemetry()
        assert t2_us != t_us
        assert dev.commanded_currents_A() == pytest.approx(currents)
        assert dev.true_force_N().shape == (info["fluid_cells"],)
        cal = dev.calibration()
        assert cal.version >= 1 and cal.profile == "mr-skin-5x5"
        assert "version" in dev.calibration_text
        dev.disable()
        assert dev.state == "disabled"
        dev.estop()
        assert dev.state == "fault"
        assert dev.counters()["telemetry"] > 0


def test_nan_and_wrong_length_currents_are_refused():
    with mrskin.open_device("mock://") as dev:
        dev.enable()
        with pytest.raises(mrskin.ResultError) as e:
            dev.set_valve_currents(np.full(dev.info["valves"], math.nan))
        assert e.value.code == "invalid_value"
        with pytest.raises(mrskin.InvalidArgument):
            dev.set_valve_currents(np.zeros(3))


@pytest.mark.parametrize(
    "uri, error",
    [
        ("bogus://x", mrskin.InvalidArgument),
        ("mock://no-such-profile", mrskin.ProfileNotFound),
        ("mock://?seed=abc", mrskin.InvalidArgument),
        ("can://?node=1", mrskin.InvalidArgument),
    ],
)
def test_bad_uris_raise_the_documented_errors(uri, error):
    with pytest.raises(error) as e:
        mrskin.open_device(uri)
    assert isinstance(e.value, mrskin.Error)
    assert str(e.value)  # says what to do


def test_one_session_per_unit():
    with mrskin.open_device("mock://"):
        with pytest.raises(mrskin.DeviceBusy):
            mrskin.open_device("mock://")
    with mrskin.open_device("mock://"):
        pass  # released by the first close


def test_closed_device_says_so():
    dev = mrskin.open_device("mock://")
    dev.close()
    with pytest.raises(mrskin.Error):
        dev.enable()
