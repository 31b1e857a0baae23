"""The contract every registered effect keeps, checked by looping over the registry: an
unknown option is refused, the force vanishes at rest (reference positions, load 0), and the
tangent is the derivative of the force (central finite differences, relative error < 1e-6).
A new effect file is checked here with no edit (its ``example`` gives required options)."""

import numpy as np
import pytest
import scipy.sparse as sp
from breastlike import breastlike_mesh

from mechanics.effects import EFFECTS, Effect
from mechanics.effects._interface import split_interface

H = 1e-6
TOL = 1e-6


@pytest.fixture(scope="module")
def split():
    return split_interface(breastlike_mesh(cells=(6, 4, 2, 2)))


def _make(name, mesh, **extra):
    cls = EFFECTS[name]
    return cls(mesh, **dict(cls.example), **extra)


def _state(mesh, rng):
    """Breast side pressed 0.05-3 mm into the muscle (contact in compression, membranes
    stretched) and slid 2 mm along x (cables taut), plus 0.01 mm noise."""
    X = mesh.nodes
    x = X + 0.01 * rng.normal(size=X.shape)
    breast = np.unique(mesh.tets[mesh.region != 2])
    x[breast, 1] += 0.05 + 0.1 * (X[breast, 1] - X[breast, 1].min())
    x[breast, 0] += 2.0 + 0.02 * X[breast, 2]  # slides along x: cables taut
    return X, x


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_unknown_option_is_refused(split, name):
    with pytest.raises(ValueError, match=rf"effect '{name}': unknown option\(s\) \['no_such'\]"):
        _make(name, split, no_such=1.0)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_declarations_are_consistent(name):
    cls = EFFECTS[name]
    params = {p.name for p in cls.params}
    options = [o.name for o in cls.option_specs]
    assert len(set(options)) == len(options) and not params & set(options)
    assert set(cls.example) <= set(options) | params
    assert set(cls.probe) <= params
    assert all(o.default in o.choices for o in cls.option_specs if o.choices)
    assert all(e in EFFECTS for e in cls.excludes)
    for p in cls.params:
        assert p.lower <= p.default <= p.upper, p.name


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_zero_force_at_rest(split, name):
    eff = _make(name, split)
    X = split.nodes
    eff.begin_step(X, X, 0.0)
    c = eff.contribute(X, X.copy(), 0.0)
    assert np.asarray(c.force).shape == X.shape
    assert np.abs(c.force).max() <= 1e-12


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_tangent_is_the_derivative_of_the_force(split, name):
    eff = _make(name, split)
    rng = np.random.default_rng(7)
    X, x = _state(split, rng)
    eff.begin_step(X, x, 1.0)
    c = eff.contribute(X, x, 1.0)
    n = 3 * len(x)
    K = sp.coo_matrix((c.vals, (c.rows, c.cols)), shape=(n, n)).toarray()
    moved = np.flatnonzero(np.any(K != 0, axis=0))
    dofs = rng.choice(moved, size=min(24, len(moved)), replace=False) if len(moved) else \
        rng.choice(n, size=12, replace=False)
    scale = max(np.abs(K).max(), np.abs(c.force).max(), 1e-300)
    for d in dofs:
        xp, xm = x.copy().reshape(-1), x.copy().reshape(-1)
        xp[d] += H
        xm[d] -= H
        fp = np.asarray(eff.contribute(X, xp.reshape(-1, 3), 1.0).force).reshape(-1)
        fm = np.asarray(eff.contribute(X, xm.reshape(-1, 3), 1.0).force).reshape(-1)
        assert np.abs((fp - fm) / (2 * H) - K[:, d]).max() <= TOL * scale, d
    if eff.load_only:
        assert len(c.vals) == 0
    elif type(eff).contribute is Effect.contribute:
        assert np.all(np.asarray(c.force) == 0)
    else:
        assert np.abs(K).max() > 0  # a structure in this state: the check is not vacuous
