"""mrskin.model: the laws against formulas written here from docs/model.md, and their errors."""
import math

import numpy as np
import pytest

import mrskin
from mrskin import model


@pytest.fixture(scope="module")
def profile():
    return model.load_profile("mr-skin-5x5")


@pytest.fixture(scope="module")
def law(profile):
    return model.ValveLaw(profile.valve, profile.fluid.viscosity_Pa_s, profile.fluid.density_kg_per_m3)


def bingham_flow(dp, tau, g, mu):
    """docs/model.md, 4: Q = (w h^3 dp / (12 mu L)) (1 - zeta)^2 (1 + zeta / 2), zeta = dp_y / |dp|."""
    dp_y = 2.0 * tau * g.length_m / g.gap_m
    if abs(dp) <= dp_y:
        return 0.0
    zeta = dp_y / abs(dp)
    return g.width_m * g.gap_m**3 * dp / (12.0 * mu * g.length_m) * (1.0 - zeta) ** 2 * (1.0 + zeta / 2.0)


def wereley_pang_pressure(q, tau, g, mu):
    """docs/model.md, 4: dp = 12 mu Q L / (w h^3) + c tau L / h, c = 2.07 + 12 Q mu / (12 Q mu + 0.4 w h^2 tau)."""
    c = 2.07 + 12.0 * q * mu / (12.0 * q * mu + 0.4 * g.width_m * g.gap_m**2 * tau)
    return 12.0 * mu * q * g.length_m / (g.width_m * g.gap_m**3) + c * tau * g.length_m / g.gap_m


DP = [1e3, 5e3, 2e4, 1e5, 4e5]
TAU = [0.0, 10.0, 100.0, 1e3]


def test_exact_flow_matches_the_bingham_law(law):
    mu = law.viscosity_Pa_s
    assert law.reynolds_number(1e-5) < 2300.0  # laminar: the formula above is the whole law
    for dp in DP:
        for tau in TAU:
            expected = bingham_flow(dp, tau, law.geometry, mu)
            got = law.flow_m3_per_s(dp, tau)
            assert got == pytest.approx(expected, rel=1e-12, abs=1e-300)
            assert law.flow_m3_per_s(-dp, tau) == pytest.approx(-expected, rel=1e-12, abs=1e-300)


def test_no_flow_below_the_yield_threshold(law):
    tau = 500.0
    dp_y = 2.0 * tau * law.geometry.length_m / law.geometry.gap_m
    assert law.yield_pressure_Pa(tau) == pytest.approx(dp_y, rel=1e-15)
    assert law.flow_m3_per_s(0.999 * dp_y, tau) == 0.0
    assert law.pressure_Pa(0.0, tau) == pytest.approx(dp_y, rel=1e-15)


def test_exact_and_fast_pressure_invert_the_flow(law):
    mu = law.viscosity_Pa_s
    for dp in DP:
        for tau in TAU[1:]:
            q = bingham_flow(dp, tau, law.geometry, mu)
            if q == 0.0:
                continue
            assert law.pressure_Pa(q, tau, method="exact") == pytest.approx(dp, rel=1e-9)
            assert law.pressure_Pa(q, tau, method="fast") == pytest.approx(dp, rel=1e-4)


def test_wereley_pang_matches_its_formula(law):
    for q in [1e-7, 1e-6, 1e-5]:
        for tau in TAU[1:]:
            expected = wereley_pang_pressure(q, tau, law.geometry, law.viscosity_Pa_s)
            assert law.pressure_Pa(q, tau, method="wereley_pang") == pytest.approx(expected, rel=1e-12)


def test_arrays_broadcast_like_numpy(law):
    dp = np.array(DP)
    got = law.flow_m3_per_s(dp[:, None], np.array(TAU)[None, :])
    assert got.shape == (len(DP), len(TAU))
    assert got[2, 3] == pytest.approx(bingham_flow(DP[2], TAU[3], law.geometry, law.viscosity_Pa_s), rel=1e-12)


def test_carlson_yield_stress(profile):
    f = profile.fluid
    for h in [0.0, 1e4, 1e5, 3e5]:
        expected = f.carrier_factor * 271700.0 * f.volume_fraction**1.5239 * math.tanh(6.33e-6 * h)
        assert model.yield_stress_Pa(f, h) == pytest.approx(expected, rel=1e-12, abs=1e-300)


def test_nan_raises_model_error_with_its_status(law, profile):
    with pytest.raises(mrskin.ModelError) as e:
        law.flow_m3_per_s(float("nan"), 0.0)
    assert e.value.status == "not_finite"
    assert isinstance(e.value, mrskin.InvalidArgument) and isinstance(e.value, ValueError)
    with pytest.raises(mrskin.ModelError):
        law.pressure_Pa(np.array([1e-6, float("nan")]), 10.0, method="fast")
    with pytest.raises(mrskin.ModelError) as e:
        model.yield_stress_Pa(profile.fluid, float("inf"))
    assert e.value.status == "not_finite"
    dm = model.DeviceModel(profile)
    with pytest.raises(mrskin.ModelError):
        dm.cell_force_uniform(0, float("nan"), 0.0, 0.1)
    with pytest.raises(mrskin.InvalidArgument):
        law.flow_m3_per_s(1e3, 0.0, method="bogus")


def test_cell_force_envelope_and_its_inverse(profile):
    dm = model.DeviceModel(profile)
    cell = dm.fluid_cell_index(2, 2)
    env = dm.envelope(cell, 4e-3, 1e-3)
    assert 0.0 < env.force_min_N < env.force_max_N
    force = 0.5 * (env.force_min_N + env.force_max_N)
    current = dm.current_for_force_A(cell, 4e-3, 1e-3, force)
    assert 0.0 < current < profile.coil.max_current_A
    assert dm.cell_force_uniform(cell, 4e-3, 1e-3, current).force_N == pytest.approx(force, rel=1e-3)
    currents = np.full(dm.valve_count, current)
    assert dm.cell_force(cell, 4e-3, 1e-3, currents).force_N == pytest.approx(force, rel=1e-3)
    with pytest.raises(mrskin.InvalidArgument):
        dm.cell_force(cell, 4e-3, 1e-3, np.zeros(3))
    with pytest.raises(mrskin.ModelError) as e:
        dm.fluid_cell_index(0, 1)  # a valve cell
    assert e.value.status == "out_of_range"


def test_profiles_list_inspect_and_errors():
    names = model.available_profiles()
    assert "mr-skin-5x5" in names
    p = model.load_profile()
    assert (p.name, p.rows, p.cols) == ("mr-skin-5x5", 5, 5)
    assert "[valve]" in model.profile_text("mr-skin-5x5")
    with pytest.raises(mrskin.ProfileNotFound) as e:
        model.load_profile("no-such-profile")
    assert "mr-skin-5x5" in str(e.value)  # lists what is there


def test_help_has_signatures_and_units():
    doc = model.ValveLaw.flow_m3_per_s.__doc__
    assert "dp_Pa" in doc and "yield_stress_Pa" in doc and "method" in doc
    assert "open_device" in mrskin.__doc__ or "mrskin.device" in mrskin.__doc__
