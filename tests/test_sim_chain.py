"""The n-mass chain, temperature-dependent stiffness and several response channels (issue 16).

Each physical statement is checked against theory built here from the equations (the chain's
matrices written out by hand, closed-form natural frequencies of a uniform chain, a static
equilibrium solved by scipy) or against the existing 2-DOF simulator, an independent code path.
The command-line tests run ``narxwatch-sim``'s entry point in this process (what it writes and
its exit code; the script as a process is ``test_sim_client``'s) with nothing listening at the
URL, so that exit code 2 shows an option was refused before any service was contacted.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
import scipy.signal

from harness.cli import invoke
from harness.live import free_port
from models.errors import InputError
from recordfiles.reader import Layout, read_record
from simulator.chain import ChainParameters, ChainScenario, integrate, simulate_chain
from simulator.client import main
from simulator.physics import PhysicalParameters, UnstableSimulationError
from simulator.simulate import Scenario, simulate
from simulator.temperature import TemperatureCycle, Thermal

TS = 6.666e-4


def rig_as_chain(p: PhysicalParameters) -> ChainParameters:
    """SPEC §1's rig: k1 grounds mass 1, k2 couples, the cubic spring k3 grounds mass 2."""
    return ChainParameters((p.m1, p.m2), (p.k1, p.k2, 0.0), (0.0, 0.0, p.k3), (p.c1, p.c2), p.ts)


def hand_matrices(p: ChainParameters) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M, C, K of the chain written from its picture, mass by mass (not from the incidence matrix)."""
    n, k = p.n, p.stiffness
    K = np.zeros((n, n))
    for i in range(n):
        K[i, i] = k[i] + k[i + 1]  # the spring on each side of mass i+1
        if i + 1 < n:
            K[i, i + 1] = K[i + 1, i] = -k[i + 1]
    return np.diag(p.masses), np.diag(p.damping), K


def run_sim(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_SIM_")}
    env |= {"NARXWATCH_SIM_URL": f"http://127.0.0.1:{free_port()}", "NARXWATCH_SIM_API_KEY": "nw_x_y"}
    return invoke(*args, cwd=cwd, check=False, script="narxwatch-sim", environ=env)


# ---------------------------------------------------------------- the chain against theory


@pytest.mark.parametrize(("fault", "k"), [("none", 0.0), ("k1", 30.0), ("k2", -20.0)])
def test_the_chain_of_two_is_the_rig(params: PhysicalParameters, fault: str, k: float) -> None:
    """The rig as the chain with n = 2 gives the rig simulator's response (both masses), its
    stability limits, and the same random draws."""
    chain = rig_as_chain(params)
    levels = {"disturbance_std": 800.0, "x_noise_std": 50.0, "temperature": 5.0}
    rig = simulate(Scenario(fault=fault, k=k, outputs=(1, 2), **levels), 3000, 9)
    record = simulate_chain(ChainScenario(chain, fault, k, **levels), 3000, 9)
    np.testing.assert_array_equal(record.x, rig.x)
    for name in ("y1", "y2"):
        np.testing.assert_allclose(
            record.responses[name], rig.responses[name], rtol=0, atol=1e-12 * np.ptp(rig.y)
        )
    # The rig takes the roots of its quartic, the chain the eigenvalues of its transition matrix.
    assert chain.linear_pole_radius == pytest.approx(params.linear_pole_radius, rel=1e-10)
    assert chain.stable_amplitude == pytest.approx(params.stable_amplitude, rel=1e-9)


def test_natural_frequencies_are_the_uniform_chains_closed_form() -> None:
    """A uniform fixed-free chain has ω_r = 2·√(k/m)·sin((2r − 1)π / (2(2n + 1))), r = 1 … n."""
    n, m, k = 5, 10.0, 50e3
    chain = ChainParameters.build(n, [m], [k], [300.0])
    r = np.arange(1, n + 1)
    closed_form = 2 * np.sqrt(k / m) * np.sin((2 * r - 1) * np.pi / (2 * (2 * n + 1))) / (2 * np.pi)
    np.testing.assert_allclose(chain.natural_frequencies(), closed_form, rtol=1e-12)


def test_the_rigs_natural_frequencies(params: PhysicalParameters) -> None:
    M, _, K = hand_matrices(rig_as_chain(params))
    expected = np.sqrt(np.sort(np.linalg.eigvals(np.linalg.solve(M, K)).real)) / (2 * np.pi)
    np.testing.assert_allclose(rig_as_chain(params).natural_frequencies(), expected, rtol=1e-12)


def test_free_decay_rings_at_the_natural_frequencies() -> None:
    """The forward-difference scheme's characteristic equation is M·σ² + C·σ + K = 0 with
    σ = (z − 1)/Ts, the continuous one with σ for s. With a damper c_i = c·m_i on every mass
    (damping proportional to mass) each mode's s² + c·s + ω_r² = 0 gives |s| = ω_r exactly, so the
    poles read off a simulated free decay (Prony: the exact AR(2n) recursion of one mass's motion)
    give the undamped natural frequencies from eigh(K, M)."""
    masses = (10.0, 20.0, 15.0)
    chain = ChainParameters(masses, (50e3, 80e3, 30e3, 20e3), (0.0,) * 4, tuple(25.0 * m for m in masses), TS)
    force = np.zeros(400)
    force[0] = 1e4
    motion = integrate(chain, force)[2:, 0]  # mass 1 after the kick
    order = 2 * chain.n
    lagged = np.column_stack([motion[order - i : len(motion) - i] for i in range(1, order + 1)])
    ar = np.linalg.lstsq(lagged, motion[order:], rcond=None)[0]
    poles = np.roots(np.concatenate(([1.0], -ar)))
    frequencies = np.sort(np.abs((poles - 1) / TS))[::2] / (2 * np.pi)  # one of each conjugate pair
    eigen = np.sqrt(scipy.linalg.eigh(hand_matrices(chain)[2], np.diag(masses), eigvals_only=True)) / (
        2 * np.pi
    )
    np.testing.assert_allclose(frequencies, eigen, rtol=1e-6)
    np.testing.assert_allclose(chain.natural_frequencies(), eigen, rtol=1e-12)


def test_frequency_response_to_a_periodic_force_is_the_transfer_function() -> None:
    """A periodic random force (the standard leakage-free FRF measurement): once the transient has
    died, each mass's response over one period is periodic, and the ratio of DFTs Y(k)/F(k) is the
    discrete transfer function [M(z−1)²/Ts² + C(z−1)/Ts + K]⁻¹·e1 at z = e^{2πik/P}, exactly."""
    chain = ChainParameters.build(3, [10.0, 20.0, 15.0], [50e3, 80e3, 30e3], [300.0])
    period = 4096  # 2.7 s; the slowest mode decays at c/2m = 7.5 /s, so 3 periods leave ~1e-26 of the start
    force = np.tile(np.random.default_rng(2).normal(0, 1e4, period), 4)
    positions = integrate(chain, force)[: len(force)]
    last = slice(len(force) - period, len(force))
    ratio = np.fft.rfft(positions[last], axis=0)[1:] / np.fft.rfft(force[last])[1:, None]
    z = np.exp(2j * np.pi * np.arange(1, period // 2 + 1) / period)
    M, C, K = hand_matrices(chain)
    theory = np.array(
        [np.linalg.solve(M * (q - 1) ** 2 / TS**2 + C * (q - 1) / TS + K, np.eye(3)[0]) for q in z]
    )
    # Rounding in the march is relative to the response's size, not to each frequency's.
    np.testing.assert_allclose(ratio, theory, rtol=1e-7, atol=1e-9 * np.abs(theory).max())


def test_mean_stored_energy_under_white_force_is_the_lyapunov_solution() -> None:
    """Energy: with the state s = (x[t], x[t+1]) the scheme is s[t+1] = T·s[t] + b·F[t], so the
    stationary covariance solves Σ = T·Σ·Tᵀ + σ²·b·bᵀ (scipy's discrete Lyapunov solver), and the
    mean stored energy ½·E[xᵀKx] + ½·E[vᵀMv], v = (x[t+1] − x[t])/Ts, follows from Σ. The
    simulated record's time average must agree within 4 standard errors (from 20 batch means;
    the standard error is about 2.5 % here, so a force or a matrix off by 10 % fails)."""
    chain = ChainParameters.build(3, [10.0, 20.0, 15.0], [50e3, 80e3, 30e3], [300.0])
    M, C, K = hand_matrices(chain)
    Minv = np.linalg.inv(M)
    A1 = 2 * np.eye(3) - TS * Minv @ C
    A0 = -np.eye(3) + TS * Minv @ C - TS**2 * Minv @ K
    T = np.block([[np.zeros((3, 3)), np.eye(3)], [A0, A1]])
    b = np.concatenate([np.zeros(3), TS**2 * Minv[:, 0]])
    sigma = 25e3
    covariance = scipy.linalg.solve_discrete_lyapunov(T, sigma**2 * np.outer(b, b))
    difference = np.hstack([-np.eye(3), np.eye(3)]) / TS
    theory = 0.5 * np.trace(K @ covariance[:3, :3]) + 0.5 * np.trace(
        M @ difference @ covariance @ difference.T
    )
    record = simulate_chain(ChainScenario(chain, excitation_std=sigma), 200_000, 0)
    X = np.column_stack([record.responses[f"y{i}"] for i in (1, 2, 3)])
    V, X = np.diff(X, axis=0) / TS, X[:-1]
    energy = 0.5 * np.einsum("ti,ij,tj->t", X, K, X) + 0.5 * np.einsum("ti,ij,tj->t", V, M, V)
    batches = energy[: len(energy) // 20 * 20].reshape(20, -1).mean(axis=1)
    standard_error = batches.std(ddof=1) / np.sqrt(20)
    assert standard_error < 0.04 * theory
    assert abs(energy.mean() - theory) < 4 * standard_error


def test_static_deflection_with_a_cubic_spring_solves_the_equilibrium() -> None:
    """A constant force settles the chain where K·x + Dᵀ·(kc⊙d³) = F·e1, solved here by scipy; the
    far wall's spring is present so that every spring carries load."""
    chain = ChainParameters(
        (10.0, 20.0, 15.0), (50e3, 80e3, 30e3, 40e3), (0.0, 2e6, 0.0, 5e6), (300.0,) * 3, TS
    )
    force = 8e3
    settled = integrate(chain, np.full(30_000, force))[-1]
    _, _, K = hand_matrices(chain)

    def imbalance(x: np.ndarray) -> np.ndarray:
        d = np.array([x[0], x[1] - x[0], x[2] - x[1], -x[2]])  # elongations, walls fixed
        cubic = np.array(chain.cubic) * d**3
        return (
            K @ x + np.array([cubic[0] - cubic[1], cubic[1] - cubic[2], cubic[2] - cubic[3]]) - [force, 0, 0]
        )

    equilibrium = scipy.optimize.fsolve(imbalance, np.linalg.solve(K, [force, 0, 0]), xtol=1e-14)
    np.testing.assert_allclose(settled, equilibrium, rtol=1e-9)
    assert not np.allclose(equilibrium, np.linalg.solve(K, [force, 0, 0]), rtol=1e-3)  # the cubic acts


def test_fixed_free_chain_deflects_as_its_first_spring() -> None:
    """With no spring at the far wall, a force on mass 1 stretches only k1: every mass moves F/k1."""
    chain = ChainParameters.build(4, [10.0], [40e3, 60e3, 50e3, 70e3], [300.0])
    settled = integrate(chain, np.full(30_000, 2e3))[-1]
    np.testing.assert_allclose(settled, 2e3 / 40e3, rtol=1e-10)


def test_acceleration_and_displacement_obey_the_equations_of_motion() -> None:
    """The two responses of one seed: the acceleration is the displacement's second difference
    over Ts², and M·a + C·v + K·x + cubic forces = F·e1 at every sample (force balance)."""
    chain = ChainParameters.build(3, [10.0, 20.0, 15.0], [50e3, 80e3, 30e3], [300.0], cubic=[0, 0, 1e6])
    shift = ChainScenario(chain, fault="k2", k=10.0)
    displacement = simulate_chain(shift, 2000, 21)
    acceleration = simulate_chain(ChainScenario(chain, fault="k2", k=10.0, response="acceleration"), 2000, 21)
    X = np.column_stack([displacement.responses[f"y{i}"] for i in (1, 2, 3)])
    A = np.column_stack([acceleration.responses[f"y{i}"] for i in (1, 2, 3)])
    np.testing.assert_allclose(
        A[:-2], np.diff(X, n=2, axis=0) / TS**2, rtol=1e-6, atol=1e-9 * np.abs(A).max()
    )
    M, C, K = hand_matrices(shift.structure)
    d3 = (X[:, 2] - X[:, 1]) ** 3
    cubic = np.column_stack([np.zeros_like(d3), -1e6 * d3, 1e6 * d3])  # spring 3 joins masses 2 and 3
    balance = A[:-1] @ M + np.diff(X, axis=0) / TS @ C + X[:-1] @ K + cubic[:-1]
    expected = np.column_stack([displacement.x[:-1], np.zeros((len(X) - 1, 2))])
    np.testing.assert_allclose(balance, expected, rtol=0, atol=1e-6 * np.abs(displacement.x).max())


def test_a_fault_scales_one_spring_and_its_cubic_part() -> None:
    chain = ChainParameters.build(5, [10.0], [50e3], [300.0], cubic=[1e6])
    faulty = chain.with_fault("k3", 20.0)
    assert faulty.stiffness == (50e3, 50e3, 40e3, 50e3, 50e3, 0.0)
    assert faulty.cubic == (1e6, 1e6, 0.8e6, 1e6, 1e6, 0.0)
    assert chain.with_fault("k3", -10.0).stiffness[2] == pytest.approx(55e3)
    with pytest.raises(InputError, match="spring k6 is absent"):
        chain.with_fault("k6", 10.0)
    with pytest.raises(InputError, match="no spring 'k9'"):
        chain.with_fault("k9", 10.0)


def test_divergence_raises_instead_of_returning_nan() -> None:
    chain = ChainParameters.build(3, [10.0], [50e3], [300.0], cubic=[1e8])
    with pytest.raises(UnstableSimulationError, match="diverged"):
        simulate_chain(ChainScenario(chain, excitation_std=5e5), 2000, 1)


@pytest.mark.parametrize(
    ("build", "fragment"),
    [
        (lambda: ChainParameters.build(3, [10.0, 20.0], [50e3], [300.0]), "--mass takes 1 or 3 values"),
        (lambda: ChainParameters.build(3, [10.0], [50e3] * 5, [300.0]), "--stiffness takes 1, 3 or 4"),
        (lambda: ChainParameters.build(3, [0.0], [50e3], [300.0]), "masses value 1 must be positive"),
        (lambda: ChainParameters.build(3, [10.0], [-1.0], [300.0]), "stiffness value 1 must be finite"),
        (lambda: ChainParameters.build(0, [10.0], [1.0], [300.0]), "1 to 50 masses"),
    ],
)
def test_bad_chains_are_refused(build, fragment: str) -> None:
    with pytest.raises(InputError, match=fragment):
        build()


# ---------------------------------------------------------------- temperature


def test_a_record_at_a_temperature_is_the_record_of_its_stiffnesses(params: PhysicalParameters) -> None:
    """k_i(T) = k_i·(1 + c_i/100·(T − 20)) with stated coefficients per spring: the record at
    −10 °C is the record of a rig whose stiffnesses are written out at −10 °C."""
    thermal = Thermal({"k2": -0.5, "k3": -0.2}, default=-0.3)
    warm = Scenario(disturbance_std=800.0, temperature=-10.0, thermal=thermal)
    by_hand = params.replace(k1=params.k1 * 1.09, k2=params.k2 * 1.15, k3=params.k3 * 1.06)
    np.testing.assert_allclose(warm.structure.k1, by_hand.k1, rtol=1e-15)
    np.testing.assert_array_equal(
        simulate(warm, 2000, 3).y, simulate(Scenario(params=by_hand, disturbance_std=800.0), 2000, 3).y
    )
    assert simulate(warm, 2000, 3).temperature == -10.0


def test_temperature_moves_the_chains_frequencies_as_the_square_root_of_stiffness() -> None:
    """One coefficient for every spring scales K, so every natural frequency by √(1 + c·ΔT)."""
    chain = ChainParameters.build(5, [10.0], [50e3], [300.0])
    cold = ChainScenario(chain, temperature=-10.0).structure  # −0.5 %/°C: 15 % stiffer
    np.testing.assert_allclose(
        cold.natural_frequencies(), chain.natural_frequencies() * np.sqrt(1.15), rtol=1e-12
    )
    faulty_cold = ChainScenario(chain, fault="k2", k=3.0, temperature=-10.0).structure
    assert faulty_cold.stiffness[1] == pytest.approx(50e3 * 0.97 * 1.15)


def test_thermal_coefficients_are_checked() -> None:
    with pytest.raises(InputError, match="names no spring of this structure: k7"):
        simulate(Scenario(temperature=0.0, thermal=Thermal({"k7": -1.0})), 10)
    with pytest.raises(InputError, match="would have no stiffness left"):
        simulate(Scenario(temperature=250.0), 10)


def test_the_temperature_cycle() -> None:
    """Warmest at 15:00 in the time's own zone and at noon on 20 July; a year spans mean ± (A + B)."""
    cycle = TemperatureCycle(10.0, daily=5.0, seasonal=15.0)
    noon_20_july = dt.datetime(2026, 7, 20, 12, tzinfo=dt.UTC)
    assert cycle.at(noon_20_july) == pytest.approx(10 + 5 * np.cos(-np.pi / 4) + 15, abs=1e-12)
    three_pm_athens = dt.datetime(2026, 7, 20, 15, tzinfo=dt.timezone(dt.timedelta(hours=3)))
    assert cycle.at(three_pm_athens) == pytest.approx(
        10 + 5 + 15 * np.cos(2 * np.pi * 0.125 / 365.2425), abs=1e-12
    )
    half_a_year_before = noon_20_july - dt.timedelta(days=365.2425 / 2)
    assert TemperatureCycle(10.0, seasonal=15.0).at(half_a_year_before) == pytest.approx(-5.0, abs=1e-9)
    year = [cycle.at(dt.datetime(2026, 1, 1, tzinfo=dt.UTC) + dt.timedelta(hours=h)) for h in range(8760)]
    assert cycle.extremes == (-10.0, 30.0)
    assert -10.0 <= min(year) < -9.99 and 29.99 < max(year) <= 30.0


# ---------------------------------------------------------------- channels and files


def test_the_rig_measures_both_masses_without_changing_y(params: PhysicalParameters) -> None:
    scenario = Scenario(disturbance_std=800.0, y_noise_std=1e-3)
    single = simulate(scenario, 2000, 5)
    both = simulate(Scenario(disturbance_std=800.0, y_noise_std=1e-3, outputs=(1, 2)), 2000, 5)
    assert list(single.responses) == ["y"] and single.responses["y"] is single.y
    assert list(both.responses) == ["y1", "y2"]
    np.testing.assert_array_equal(both.responses["y2"], single.y)
    np.testing.assert_array_equal(both.x, single.x)
    noise_free = simulate(Scenario(disturbance_std=800.0, outputs=(1, 2)), 2000, 5)
    mass1 = simulate_chain(ChainScenario(rig_as_chain(params), disturbance_std=800.0, outputs=(1,)), 2000, 5)
    np.testing.assert_allclose(noise_free.responses["y1"], mass1.responses["y1"], rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="masses of the 2-DOF rig, 1 or 2; got 3"):
        simulate(Scenario(outputs=(3,)), 10)


def test_stream_writes_channels_and_each_records_temperature_from_its_time(tmp_path: Path) -> None:
    """A year's stream in one run (--no-wait): each record's temperature is the cycle's at its
    acquisition time, in the manifest, the JSON lines and the file's comment line, and the
    physics used it; the CSV's columns y1 … y5 are read by the service's reader one by one."""
    start = dt.datetime(2026, 1, 1, 3, tzinfo=dt.UTC)
    args = ["stream", "--masses", "5", "--temperature", "10", "--daily-amplitude", "5"]
    args += ["--seasonal-amplitude", "15", "--every", str(91 * 86400 + 6 * 3600), "--count", "3"]
    args += ["--no-wait", "--acquired-at", start.isoformat(), "--seed", "40", "--out", "d", "--json"]
    result = run_sim(*args, "--fault", "k4", "--k", "5", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    cycle = TemperatureCycle(10.0, 5.0, 15.0)
    times = [start + dt.timedelta(seconds=i * (91 * 86400 + 6 * 3600)) for i in range(3)]
    expected = [cycle.at(t) for t in times]
    assert [json.loads(line)["temperature"] for line in result.stdout.splitlines()] == expected
    with (tmp_path / "d" / "manifest.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [float(row["temperature"]) for row in rows] == expected
    assert max(expected) - min(expected) > 20  # winter night to a summer afternoon
    chain = ChainParameters.build(5, [10.0], [50e3], [300.0])
    for row, temperature, seed in zip(rows, expected, (40, 41, 42), strict=True):
        path = tmp_path / "d" / row["path"]
        assert f"# temperature={temperature:.17g} °C\n" in path.read_text()
        again = simulate_chain(
            ChainScenario(chain, "k4", 5.0, temperature=temperature),
            2000,
            seed,  # no unmeasured force
        )
        for name in ("y1", "y3", "y5"):
            np.testing.assert_array_equal(read_record(path, Layout(y=name)).y, again.responses[name])


def test_npz_records_hold_each_channel_and_the_temperature(tmp_path: Path) -> None:
    args = ["record", "--outputs", "both", "--temperature", "-5", "--seed", "8", "--format", "npz"]
    result = run_sim(*args, "--out", "d", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    with np.load(tmp_path / "d" / "record_0001_none_0.npz") as npz:
        assert sorted(npz.files) == ["fs", "temperature", "x", "y1", "y2"]
        expected = simulate(Scenario(disturbance_std=800.0, temperature=-5.0, outputs=(1, 2)), 2000, 8)
        np.testing.assert_array_equal(npz["y1"], expected.responses["y1"])
        np.testing.assert_array_equal(npz["y2"], expected.y)
        assert float(npz["temperature"]) == -5.0 and float(npz["fs"]) == 1500.0


def test_a_manifest_without_temperatures_is_not_mixed_with_records_that_have_one(tmp_path: Path) -> None:
    assert run_sim("record", "--seed", "1", "--out", "d", cwd=tmp_path).returncode == 0
    mixed = run_sim("record", "--seed", "2", "--temperature", "3", "--out", "d", cwd=tmp_path)
    assert mixed.returncode == 2 and "not a manifest of such records" in mixed.stderr
    assert sorted(p.name for p in (tmp_path / "d").iterdir()) == ["manifest.csv", "record_0001_none_0.csv"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["record", "--masses", "9"],
            "these records have 9 response channels and the service takes at most 8",
        ),
        (["record", "--mass", "3", "--out", "d"], "--mass: options of the chain"),
        (
            ["record", "--masses", "3", "--param", "k1=1", "--out", "d"],
            "--effect and --param act on the 2-DOF rig",
        ),
        (
            ["record", "--masses", "3", "--stiffness", "1,2", "--out", "d"],
            "--stiffness takes 1, 3 or 4 values",
        ),
        (["record", "--masses", "3", "--mass", "1,x", "--out", "d"], "--mass '1,x': write one number"),
        (["record", "--masses", "3", "--outputs", "4", "--out", "d"], "masses of the chain, 1 … 3; got 4"),
        (["record", "--outputs", "3", "--out", "d"], "masses of the 2-DOF rig, 1 or 2; got 3"),
        (["record", "--masses", "3", "--fault", "k4", "--out", "d"], "spring k4 is absent"),
        (["record", "--masses", "3", "--response", "speed", "--out", "d"], "--response 'speed'"),
        (["record", "--masses", "3", "--damping", "1", "--out", "d"], "unstable for this chain"),
        (["record", "--masses", "51", "--out", "d"], "Invalid value for '--masses'"),
        (["stream", "--daily-amplitude", "3", "--out", "d"], "give it with --temperature"),
        (["record", "--thermal-coefficient", "k2=-1", "--out", "d"], "acts only at a temperature"),
        (
            ["record", "--temperature", "0", "--thermal-coefficient", "k4=-1"],
            "names no spring of this structure: k4",
        ),
        (
            ["record", "--temperature", "0", "--thermal-coefficient", "k2"],
            "cannot read thermal coefficient 'k2'",
        ),
        (["stream", "--temperature", "10", "--seasonal-amplitude", "300", "--out", "d"], "no stiffness left"),
        (["stream", "--no-wait", "--out", "d"], "--no-wait needs --acquired-at"),
    ],
)
def test_bad_combinations_exit_2_naming_what_to_fix(
    args: list[str],
    message: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
) -> None:
    """The console script's entry point run in this process (a subprocess each would take a
    second): nothing listens at the URL, so exit code 2 shows the options were refused first."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["narxwatch-sim", *args])
    monkeypatch.setenv("NARXWATCH_SIM_URL", f"http://127.0.0.1:{free_port()}")
    monkeypatch.setenv("NARXWATCH_SIM_API_KEY", "nw_x_y")
    with pytest.raises(SystemExit) as exit_:
        main()
    stderr = capsys.readouterr().err
    assert exit_.value.code == 2, stderr
    assert message in " ".join(stderr.split()) and "Traceback" not in stderr
    assert list(tmp_path.iterdir()) == []
