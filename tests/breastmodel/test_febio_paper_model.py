"""The paper's model (supports, ligaments, skin, fascia; bonded interface) on two breast mounds
on a muscle slab, solved by our solver and by FEBio from our writer's file: the same physics
gives the same displacements, and where FEBio's shells stand for our membranes the difference
is FEBio's shell discretisation, shrinking with refinement. Both codes use standard linear
tets, so the bulk discretisation is the same. Needs FEBio; skipped without it."""

import numpy as np

from breastmodel.febio import solve_with_febio
from breastmodel.phantom.mounds import mound_mesh
from mechanics.model import build_model
from mechanics.solver import SolverOptions, solve

COARSE, FINE = (12, 8, 4, 2), (26, 16, 6, 2)  # 3456 and 19968 tets


def paper_model(cells, *, membranes: tuple[str, ...]):
    """Prone: breasts 1 kPa, muscle 10 kPa, the paper's supports and ligaments (100 kPa), and
    the named membranes (skin 4 kPa x 2 mm with the plain law, fascia 120 kPa x 0.1 mm)."""
    mesh = mound_mesh(cells=cells, gland=False)
    nh = {"name": "neo_hookean", "nu": 0.49}
    effects = {"gravity": {"direction": (0, -1, 0), "g": 9.81, "density": 1000.0},
               "supports": {}, "ligaments": {"E": 100.0}}
    membrane = {"skin": {"E": 4.0, "thickness": 2.0, "wrinkling": "none"},
                "fascia": {"E": 120.0, "thickness": 0.1}}
    effects.update({k: membrane[k] for k in membranes})
    return build_model(mesh, {1: {**nh, "E": 1.0}, 2: {**nh, "E": 10.0}, 3: {**nh, "E": 1.0}},
                       effects, formulation="standard")


def difference(model, febio, work) -> tuple[np.ndarray, float]:
    """|u_FEBio - u_ours| per node (mm) and max |u_ours| (mm)."""
    ours = solve(model, options=SolverOptions(tol=1e-10))
    run = solve_with_febio(model, work_dir=work, febio=febio, element="tet4", steps=4,
                           threads=2, etol=1e-10)
    assert ours.converged and run.converged
    return (np.linalg.norm(run.displacement - ours.u, axis=1),
            float(np.linalg.norm(ours.u, axis=1).max()))


def test_supports_and_ligaments_give_our_displacements(febio, tmp_path):
    """Without membranes every part of the paper's model is the same physics in both codes
    (supports as fixed components, ligaments as tension-only springs): FEBio gives our
    displacement field to solver tolerance. Measured: max |u| 2.90 mm, difference 4e-11 mm."""
    diff, scale = difference(paper_model(COARSE, membranes=()), febio, tmp_path)
    print(f"max |u| {scale:.3f} mm, max |u_FEBio - u_ours| {diff.max():.2e} mm")
    assert scale > 1.0
    assert diff.max() < 1e-6 * scale


def test_skin_difference_is_febio_shell_discretisation(febio, tmp_path):
    """With the skin, FEBio's thinned shells keep a transverse shear stiffness that our
    membrane has not; it is a discretisation effect of FEBio's tri3 shells, so it shrinks with
    refinement. Measured (prone, 99th percentile / worst node, % of max |u|): 3456 tets
    2.97 / 3.77, 19968 tets 1.53 / 2.25. With the fascia too, the shells' single director at
    the nodes where skin and fascia meet (the model's cut edges) adds a local peak there
    (19968 tets, supine: worst node 7.4 % at x = -100 mm, 99th percentile 2.8 %)."""
    coarse, s_coarse = difference(paper_model(COARSE, membranes=("skin",)), febio,
                                  tmp_path / "coarse")
    fine, s_fine = difference(paper_model(FINE, membranes=("skin",)), febio, tmp_path / "fine")
    p_coarse, p_fine = np.percentile(coarse, 99) / s_coarse, np.percentile(fine, 99) / s_fine
    print(f"|u_FEBio - u_ours| p99 / max, % of max |u|: coarse "
          f"{p_coarse:.2%} / {coarse.max() / s_coarse:.2%}, fine {p_fine:.2%} / "
          f"{fine.max() / s_fine:.2%}")
    assert p_fine < 0.7 * p_coarse
    assert fine.max() / s_fine < 0.7 * coarse.max() / s_coarse
    assert p_fine < 0.02
