"""ident.fueldelay: the fractional fuel shift and seed 2's sweep."""
import numpy as np

from fuelid.ident.fueldelay import shift_signal, sweep_fuel_shift


def test_fractional_shift_and_sweep_find_a_hidden_delay():
    """Seed 2's static model and ±1 s sweep: a 0.4 s fuel delay is found within ±0.1 s."""
    rng = np.random.default_rng(3)
    ts, n = 0.3, 6000
    t = np.arange(n) * ts
    speed = 600 + 1300 * np.abs(np.sin(t / 37)) + np.convolve(rng.normal(0, 60, n), np.ones(5) / 5, "same")
    torque = 800 + 700 * np.sin(t / 11 + 1) + np.convolve(rng.normal(0, 100, n), np.ones(3) / 3, "same")
    fuel = 2.5 + 0.002 * (speed - 600) + 0.03 * torque + 1e-5 * (speed - 600) * torque / 10
    measured = shift_signal(fuel, -0.4 / ts) + rng.normal(0, 0.3, n)  # lags by 0.4 s

    def static_rmse(tau):
        y = shift_signal(measured, tau / ts)
        X = np.column_stack([np.ones(n), speed, torque, speed * torque, speed**2, torque**2])
        r = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        return float(np.sqrt(np.mean(r[10:-10] ** 2)))

    sweep = sweep_fuel_shift(static_rmse)
    assert abs(sweep["best_s"] - 0.4) <= 0.1
    assert len(sweep["shifts_s"]) == 21
