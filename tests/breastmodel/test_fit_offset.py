"""The fit's sensitivity to a segmentation bias: how far a measured skin offset along its
normal moves the fitted parameters (issue 15: an uncertainty that includes the
segmentation's, not the skin's noise alone)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from breastmodel.pipeline import fit as fitmod
from breastmodel.pipeline import fit_jacobian
from breastmodel.pipeline import problem as problem_mod
from breastmodel.pipeline.fit_statistics import offset_sensitivity
from breastmodel.pipeline.scoring import RIM_FADE_MM, fit_residual, skin_residual

E_OPT, S_OPT = 0.93, 7.4  # kPa
PARAMS = {"materials.breast_left.E": {"min": 0.1, "max": 4.0, "step": 0.1},
          "effects.skin.E": {"min": 1.0, "max": 20.0, "step": 1.0}}


def _patch():
    """A 40 x 40 mm flat measured skin in z = 0 (outward +z), 2 mm triangles."""
    n = 21
    g = np.linspace(0.0, 40.0, n)
    V = np.array([[x, y, 0.0] for y in g for x in g])
    q = [(i + n * j, i + 1 + n * j, i + 1 + n * (j + 1), i + n * (j + 1))
         for j in range(n - 1) for i in range(n - 1)]
    return V, np.array([t for a, b, c, d in q for t in ((a, b, c), (a, c, d))])


def test_the_offset_slope_is_how_the_residual_changes_when_the_measured_skin_moves_out():
    V, F = _patch()
    # above and below the interior, and near the rim where the residual fades
    pts = np.array([[20.0, 20.0, 3.0], [20.0, 20.0, -2.0], [40.0 - RIM_FADE_MM / 2, 20.0, 1.0],
                    [39.5, 39.5, 0.5], [10.0, 1.0, -4.0]])
    lm = (["a", "b"], np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]), np.zeros((2, 3)))
    for sees, n_lm in ((["skin"], 0), (["skin", "landmarks"], 6), (["landmarks"], 6)):
        r0, g = fit_residual(pts, (V, F), lm if n_lm else None, sees)
        moved = V + [0.0, 0.0, 0.25]  # the measured skin 0.25 mm further out
        r1, _ = fit_residual(pts, (moved, F), lm if n_lm else None, sees)
        assert len(r0) == len(g) == (5 if "skin" in sees else 0) + n_lm
        assert np.allclose((r1 - r0) / 0.25, g, atol=1e-9)
        if n_lm:  # the landmarks do not see the skin
            assert np.all(g[len(g) - n_lm:] == 0.0)
    # on the skin alone the slope is minus the rim fade: -1 inside, -1/2 half-way to the rim
    _, g = fit_residual(pts, (V, F), None, ["skin"])
    r, fade = skin_residual(pts, V, F, with_fade=True)
    assert np.allclose(g, -fade) and g[0] == -1.0 and g[2] == pytest.approx(-0.5, abs=0.03)
    assert np.allclose(r, skin_residual(pts, V, F))


def _offset_residual(*, offset_mm: float, seed: int = 5):
    """(A, g, noise, evaluate): 300 skin residuals A z + noise + offset_mm g in z = ln(p /
    p_opt), where g is the residual's change per mm of outward skin offset (minus a rim fade,
    1 on most nodes). A 10 % stiffer breast lifts the skin by about 1 mm, as on the suite's
    small subjects, so a 1 mm offset moves the fitted modulus by about 10 %."""
    rng = np.random.default_rng(seed)
    A = np.column_stack([10.0 * (1.0 + 0.3 * rng.normal(size=300)), 3.0 * rng.normal(size=300)])
    g = -np.clip(rng.uniform(0.0, 4.0, size=300), 0.0, 1.0)
    noise = 0.05 * rng.normal(size=300)

    def evaluate(params, problem_dir, settings, residuals=False, **kw):
        z = np.array([math.log(params["materials.breast_left.E"] / E_OPT),
                      math.log(params["effects.skin.E"] / S_OPT)])
        r = A @ z + noise + offset_mm * g
        return {"objective": float(np.mean(np.abs(r))), "mhd_mm": {"prone": 0.0},
                "forward_solves": 4, "error": None, "residual": {"prone": r.tolist()},
                "residual_offset": {"prone": g.tolist()}}
    return A, g, noise, evaluate


def test_least_squares_reports_how_far_a_skin_offset_moves_the_fitted_moduli(monkeypatch,
                                                                             tmp_path):
    """The reported change per mm equals the exact linear model's, and a fit on a skin
    really offset by 1 mm lands where it said."""
    x0 = {"materials.breast_left.E": 2.5, "effects.skin.E": 2.0}
    fits = []
    for s in (0.0, 1.0):
        A, g, noise, evaluate = _offset_residual(offset_mm=s)
        monkeypatch.setattr(problem_mod, "evaluate_params", evaluate)
        fits.append(fitmod.least_squares(tmp_path, {"calibrate": ["prone"]}, PARAMS, budget=40,
                                         work_dir=tmp_path / f"w{s:g}", x0=x0))
    sens = fits[0]["skin_offset_sensitivity"]
    assert set(sens) == set(PARAMS)
    z_hat = np.linalg.lstsq(A, -noise, rcond=None)[0]  # the exact optimum without offset
    dz = np.linalg.lstsq(A, -g, rcond=None)[0]  # its exact shift per mm of offset
    assert 0.05 < dz[0] < 0.3  # the breast modulus moves by several per cent
    p_hat = np.array([E_OPT, S_OPT]) * np.exp(z_hat)
    for k, name in enumerate(PARAMS):
        assert sens[name] == pytest.approx(p_hat[k] * dz[k], rel=0.02)
        p0, p1 = (f["best"]["params"][name] for f in fits)
        # the offset fit lands at exp(dz) times the first, each fit within its precision (it
        # stops once a step moves every parameter by less than STOP_STEP, 1 %)
        assert abs(p1 / p0 - math.exp(dz[k])) <= 2 * fit_jacobian.STOP_STEP


def test_offset_sensitivity_refuses_what_it_cannot_compute():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(50, 2))
    names = ["a", "b"]
    assert offset_sensitivity(J, np.ones(49), np.ones(2), names) == {}  # lengths differ
    assert offset_sensitivity(np.column_stack([J[:, 0], J[:, 0]]), np.ones(50), np.ones(2),
                              names) == {}  # the data cannot separate the two
    # a residual column equal to the slope: that parameter absorbs the offset alone
    out = offset_sensitivity(np.column_stack([-np.ones(50), J[:, 1]]), -np.ones(50),
                             np.array([2.0, 3.0]), names)
    assert out["a"] == pytest.approx(-2.0) and out["b"] == pytest.approx(0.0, abs=1e-12)
