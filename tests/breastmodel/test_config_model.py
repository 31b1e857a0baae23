"""The whole ``[model]`` table is validated when the config is read, before any stage runs:
unknown effects, options and materials, wrong types and out-of-bounds values are refused with
the file, the table and the key in the message, using the registries' units and bounds."""

from pathlib import Path

import pytest

from breastmodel.config import ConfigError
from breastmodel.pipeline.config import DEFAULTS, load_run_config, resolve_config

ROOT = Path(__file__).resolve().parents[2]
MATS = DEFAULTS["model"]["materials"]


def _model(effects=None, **materials):
    return {"model": {"materials": {**MATS, **materials},
                      "effects": {"fixed": {"node_set": "fixed"}, **(effects or {})}}}


@pytest.mark.parametrize("raw,match", [
    (_model({"skn": {}}), r"\[model\.effects\.skn\]: unknown effect 'skn'"),
    (_model({"skin": {"lw": "gent"}}), r"\[model\.effects\.skin\]: unknown key 'lw'"),
    (_model({"skin": {"E": 100.0}}), r"\[model\.effects\.skin\] E = 100\.0 kPa is outside "
                                     r"\[1\.0, 20\.0\] kPa"),
    (_model({"skin": {"E": "four"}}), r"\[model\.effects\.skin\] E must be a number \(kPa\)"),
    (_model({"skin": {"law": "mooney"}}), r"\[model\.effects\.skin\] law: .*must be one of"),
    (_model({"ligaments": {"groups": "medial"}}),
     r"\[model\.effects\.ligaments\] groups must be of type list or tuple"),
    (_model({"supports": {"muscle": "yes"}}), r"\[model\.effects\.supports\] muscle must be "
                                              r"of type bool"),
    (_model({"gravity": {}}), r"\[model\.effects\.gravity\]: gravity is set per position"),
    (_model(breast_left={"name": "rubber"}),
     r"\[model\.materials\.breast_left\]: unknown material 'rubber'"),
    (_model(breast_left={"name": "neo_hookean", "E": "one"}),
     r"\[model\.materials\.breast_left\] E must be a number \(kPa\), got 'one'"),
    (_model(breast_left={"name": "neo_hookean", "E": 1.0, "nu": 0.5}),
     r"\[model\.materials\.breast_left\] nu = 0\.5 - is outside"),
    (_model(breast_left={"name": "neo_hookean", "Jm": 1.0}),
     r"\[model\.materials\.breast_left\]: unknown key 'Jm'"),
])
def test_bad_model_table_is_refused(raw, match):
    with pytest.raises(ConfigError, match=match):
        resolve_config(raw)


def test_the_message_names_the_file(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('[model.effects.skin]\nE = "four"\n')
    with pytest.raises(ConfigError, match=rf"run: {path}.*\[model\.effects\.skin\] E must"):
        load_run_config(path)


def test_the_example_and_the_defaults_pass():
    cfg = load_run_config(ROOT / "examples" / "run.toml")
    assert cfg["model"]["effects"]
    assert resolve_config({})["model"] == DEFAULTS["model"]


def test_a_list_of_tables_is_checked_table_by_table():
    raw = _model({"fixed": [{"node_set": "fixed"}, {"node_set": "fixed", "bogus": 1}]})
    with pytest.raises(ConfigError, match=r"\[model\.effects\.fixed #2\]: unknown key 'bogus'"):
        resolve_config(raw)


def test_a_new_effect_with_options_is_one_class(monkeypatch):
    """Everything the config, the problem builder and the diagnosis need comes from the
    class: its options are accepted and checked, its split and probe declarations are read."""
    from breastmodel.diagnosis.candidates import enumerate_candidates
    from mechanics.effects import EFFECTS, Effect, Option, Param, needs_split_interface

    class Prestress(Effect):
        name = "test_prestress"
        params = (Param("sigma", "kPa", 0.5, 0.0, 5.0),)
        option_specs = (Option("axis", "z", "direction of the prestress", ("x", "y", "z"),
                               (str,)),)
        probe = {"sigma": 2.0}
        split_interface = True

    monkeypatch.setitem(EFFECTS, Prestress.name, Prestress)
    cfg = resolve_config(_model({"test_prestress": {"sigma": 1.0, "axis": "x"}}))
    assert cfg["model"]["effects"]["test_prestress"] == {"sigma": 1.0, "axis": "x"}
    with pytest.raises(ConfigError, match=r"\[model\.effects\.test_prestress\] axis: "):
        resolve_config(_model({"test_prestress": {"axis": "w"}}))
    assert needs_split_interface(["fixed", "test_prestress:2"])
    cand = next(c for c in enumerate_candidates(_model()["model"])[0]
                if c.name == "test_prestress")
    assert cand.effects == {"test_prestress": {"sigma": 2.0}}
    assert cand.start == {"effects.test_prestress.sigma": 2.0}


def test_solver_table_takes_every_solver_option_and_refuses_the_rest():
    """The [solver] keys are the solver's own option fields, so a new option is settable
    from run.toml without a second list to keep in step."""
    from dataclasses import fields

    from mechanics.solver import SolverOptions

    names = {f.name for f in fields(SolverOptions)}
    assert {"reuse_factor", "reuse_below", "reuse_max_iterations", "progress"} <= names
    cfg = resolve_config({"solver": {"reuse_factor": False, "reuse_max_iterations": 40}})
    assert SolverOptions(**cfg["solver"]).reuse_factor is False
    with pytest.raises(ConfigError, match=r"\[solver\].*reuse_factr"):
        resolve_config({"solver": {"reuse_factr": False}})
