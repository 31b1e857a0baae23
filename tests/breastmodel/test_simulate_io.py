"""VTU round trip of a solved state (meshing.export, mechanics.export) and the
``breastmodel simulate`` command."""

import json

import numpy as np
import pytest
from zoo import hemisphere

from mechanics.export import result_fields
from mechanics.model import build_model
from mechanics.solver import SolverOptions, solve
from meshing.export import read_vtu, write_vtu

pytest.importorskip("meshio")


def test_vtu_round_trip_with_state(tmp_path):
    import meshio

    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, {1: {"name": "gent", "E": 1.0, "nu": 0.49, "Jm": 5.0}},
                        {"gravity": {"direction": (1, 0, 0)}, "fixed": {"node_set": "fixed"}})
    st = solve(model, options=SolverOptions(linear_solver="scipy"))
    pts, fields, cells = result_fields(mesh, st)
    write_vtu(tmp_path / "r.vtu", mesh, points=pts, fields=fields, cell_fields=cells)
    back = read_vtu(tmp_path / "r.vtu")
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.region, mesh.region)
    np.testing.assert_array_equal(back.node_sets["fixed"], mesh.node_sets["fixed"])
    raw = meshio.read(tmp_path / "r.vtu")
    np.testing.assert_allclose(raw.point_data["displacement"], st.u)
    stretch = raw.cell_data["stretch"][0]
    assert stretch.shape == (mesh.n_tets, 3) and np.all(stretch[:, 0] >= stretch[:, 2])
    np.testing.assert_allclose(raw.cell_data["stress"][0], st.stress.reshape(-1, 9))


def test_read_vtu_errors(tmp_path):
    with pytest.raises(OSError, match="does not exist"):
        read_vtu(tmp_path / "missing.vtu")
    (tmp_path / "bad.vtu").write_text("not a mesh")
    with pytest.raises(ValueError, match="cannot read mesh"):
        read_vtu(tmp_path / "bad.vtu")


def test_simulate_command(tmp_path, capsys):
    from breastmodel.cli import main

    mesh = hemisphere(60.0, 4)
    write_vtu(tmp_path / "mesh.vtu", mesh)
    (tmp_path / "sim.toml").write_text(
        '[model.materials.breast_left]\nname = "neo_hookean"\nE = 1.0\nnu = 0.49\n\n'
        '[model.effects.fixed]\nnode_set = "fixed"\n\n'
        '[gravity]\ndirection = [0, 0, -1]\n\n'
        '[solver]\nlinear_solver = "scipy"\n'
    )
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "mesh.vtu"), "--config", str(tmp_path / "sim.toml"),
                 "--out", str(out)]) == 0
    summary = json.loads((out / "solve.json").read_text())
    assert summary["converged"] and summary["newton_iterations"] >= 2
    import meshio

    u = meshio.read(out / "result.vtu").point_data["displacement"]
    assert u.shape == (mesh.n_nodes, 3)
    assert abs(np.linalg.norm(u, axis=1).max() - summary["max_displacement_mm"]) < 1e-9
    assert u[:, 2].min() < -1.0
    st = summary["stats"]
    assert st["linear_solver"] == "scipy" and st["peak_rss_mb"] > 0 and st["factorizations"]
    assert all("t_factor" in e and "cpu_by_effect" in e for e in summary["log"])
    # [solver] threads reaches the solver (PARDISO's thread count), reported in solve.json.
    pytest.importorskip("pypardiso")
    (tmp_path / "t.toml").write_text((tmp_path / "sim.toml").read_text().replace(
        '"scipy"', '"pardiso"\nthreads = 1'))
    assert main(["simulate", str(tmp_path / "mesh.vtu"), "--config", str(tmp_path / "t.toml"),
                 "--out", str(out)]) == 0
    st = json.loads((out / "solve.json").read_text())["stats"]
    assert st["linear_solver"] == "pardiso" and st["threads"] == 1
    # A typo in the config is one clear error, exit code 1.
    (tmp_path / "typo.toml").write_text('[model.materials.breast_left]\nname = "neo_hookean"\n'
                                        '[gravty]\n')
    assert main(["simulate", str(tmp_path / "mesh.vtu"), "--config",
                 str(tmp_path / "typo.toml"), "--out", str(out)]) == 1
    # The model tables are run.toml's, validated alike: the message names file, table, key.
    (tmp_path / "bad.toml").write_text('[model.materials.breast_left]\nname = "neo_hookean"\n'
                                       'EE = 1.0\n')
    capsys.readouterr()
    assert main(["simulate", str(tmp_path / "mesh.vtu"), "--config",
                 str(tmp_path / "bad.toml"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert str(tmp_path / "bad.toml") in err and "[model.materials.breast_left]" in err
    assert "'EE'" in err


def test_simulate_former_dialect_still_solves_with_a_warning(tmp_path):
    """Materials keyed by region code, [[supports]] and density in [gravity]: read as before,
    with a FutureWarning naming the new tables; the same model in the new form gives the
    same displacement."""
    import meshio

    from breastmodel.simulate import simulate_file

    mesh = hemisphere(60.0, 4)
    write_vtu(tmp_path / "mesh.vtu", mesh)
    solver = {"linear_solver": "scipy", "tol": 1e-8, "max_newton": 20, "initial_steps": 1,
              "max_cutbacks": 20}
    old = {"materials": {"1": {"name": "neo_hookean", "E": 1.0, "nu": 0.49}},
           "supports": [{"node_set": "fixed"}],
           "gravity": {"direction": [1, 0, 0], "density": 1000.0, "g": 9.81},
           "solver": {"linear_solver": "scipy"}}
    with pytest.warns(FutureWarning, match=r"\[model.materials.<region name>\]"):
        simulate_file(tmp_path / "mesh.vtu", old, tmp_path / "old")
    new = {"model": {"materials": {"breast_left": {"name": "neo_hookean", "E": 1.0,
                                                   "nu": 0.49}},
                     "effects": {"fixed": {"node_set": "fixed"}}},
           "gravity": {"direction": [1, 0, 0]}, "solver": solver}
    simulate_file(tmp_path / "mesh.vtu", new, tmp_path / "new")
    u_old, u_new = (meshio.read(tmp_path / d / "result.vtu").point_data["displacement"]
                    for d in ("old", "new"))
    np.testing.assert_allclose(u_new, u_old, rtol=0, atol=1e-9)
