"""The run config (``run.toml``): defaults, validation and parameter paths.

Every table is optional; :func:`resolve_config` fills the defaults and rejects unknown keys,
so the resolved dict is what the stages hash and what ``DIR/config.toml`` records. See
``examples/run.toml`` for every key with its meaning.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

from breastmodel.config import ConfigError, check_keys, load_toml
from breastmodel.pipeline.register import REGISTER_KEYS
from breastmodel.pipeline.segment import PREPROCESS_KEYS, SEGMENT_KEYS
from mechanics.solver import SolverOptions

__all__ = [
    "DEFAULTS", "FIT_PARAMETER_KEYS", "GIVEN_LABEL_KEYS", "check_model", "get_param",
    "given_labels", "load_run_config", "materials_by_code", "resolve_config", "set_params",
]

# the stages' own keys, so that run.toml and the stage commands accept the same tables: a
# run takes its positions from the subject and may give label maps instead (corrected ones,
# or a phantom's truth), for every position or for those in ``labels_positions``
#: the run's own [segment] keys: label maps given instead of segmenting
GIVEN_LABEL_KEYS = ("labels", "labels_positions")
_SEGMENT_KEYS = (SEGMENT_KEYS - {"positions"}) | set(GIVEN_LABEL_KEYS)
_PREPROCESS_KEYS = PREPROCESS_KEYS
_REGISTER_KEYS = REGISTER_KEYS
#: every option of the solver (:class:`mechanics.solver.SolverOptions`), by its field names
_SOLVER_KEYS = {f.name for f in fields(SolverOptions)}
FIT_PARAMETER_KEYS = {"min", "max", "step", "values"}

#: The defaults: a Neo-Hookean breast (1 kPa), a stiff muscle layer (10 kPa), fixed chest
#: wall (also where the reference scan cut it: ``mechanics.effects.cut_faces``), the mesh
#: sized by the breast ("auto"), the full-field inverse for the stress-free geometry, no
#: fitting.
DEFAULTS: dict[str, Any] = {
    "preprocess": {},
    "segment": {},
    "register": {"require_fiducials": True},
    "mesh": {"size_mm": "auto", "keep_gland": False, "threads": 1},
    "surface": {"edge_mm": 2.0},
    "model": {
        "formulation": "anp",
        "density": 1000.0,
        "g": 9.81,
        "materials": {
            "breast_left": {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
            "breast_right": {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
            "muscle": {"name": "neo_hookean", "E": 10.0, "nu": 0.49},
        },
        "effects": {"fixed": {"node_set": "fixed"}, "cut_faces": {}},
    },
    "solver": {"tol": 1e-6, "max_newton": 25, "initial_steps": 2, "max_cutbacks": 12},
    "stress_free": {"method": "inverse", "position": None, "lam": 0.5, "tol_mm": 0.05,
                    "max_iter": 30, "anderson": 5, "min_improvement_mm": 0.01},
    "evaluate": {"positions": None, "refinement": False},
    "fit": {"enabled": False, "calibrate": None, "evaluate": None, "method": "optimizer",
            "budget": 100, "parameters": {}, "n_workers": 1, "scheduler": None,
            "sensitivity": True, "sees": ["skin"], "stress_free_tol_mm": 0.005},
}

_TABLE_KEYS = {
    "preprocess": _PREPROCESS_KEYS, "segment": _SEGMENT_KEYS, "register": _REGISTER_KEYS,
    "mesh": {"size_mm", "keep_gland", "threads"}, "surface": {"edge_mm"},
    "model": {"formulation", "density", "g", "materials", "effects"},
    "solver": _SOLVER_KEYS,
    "stress_free": {"method", "position", "lam", "tol_mm", "max_iter", "anderson",
                    "min_improvement_mm"},
    "evaluate": {"positions", "refinement"},
    "fit": {"enabled", "calibrate", "evaluate", "method", "budget", "parameters", "n_workers",
            "scheduler", "sensitivity", "sees", "stress_free_tol_mm"},
}


# What a fit may compare with the measurements: the skin surfaces (signed node-to-surface
# distances) and the internal landmarks of ``landmarks.csv`` (predicted minus measured).
FIT_SEES = ("skin", "landmarks")


def _merge(base: dict, over: Mapping) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict) and k not in (
                "materials", "effects", "parameters"):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(dict(v) if isinstance(v, Mapping) else v)
    return out


def resolve_config(raw: Mapping[str, Any] | None = None, *, where: str = "run config") -> dict:
    """Defaults + ``raw``, validated.

    ``[model.materials]`` and ``[model.effects]`` REPLACE the defaults when given (a config
    lists the whole model); every other table is merged key by key.

    Raises
    ------
    ConfigError
        Unknown table or key, a bad model table (:func:`check_model`), bad stress-free
        method or fit settings.
    """
    raw = dict(raw or {})
    check_keys(raw, _TABLE_KEYS, where=where)
    for name, table in raw.items():
        if not isinstance(table, Mapping):
            raise ConfigError(f"{where}: [{name}] must be a table")
        check_keys(table, _TABLE_KEYS[name], where=f"{where} [{name}]")
    cfg = _merge(DEFAULTS, raw)
    check_model(cfg["model"], where=where)
    _check_given_labels(cfg["segment"], where)
    _check_register(cfg["register"], where)
    sf = cfg["stress_free"]
    if sf["method"] not in ("inverse", "paper", "none"):
        raise ConfigError(f"{where} [stress_free] method must be 'inverse', 'paper' or "
                          f"'none', got {sf['method']!r}")
    size = cfg["mesh"]["size_mm"]
    if size != "auto" and (isinstance(size, bool) or not isinstance(size, int | float)
                           or not 0.5 <= size <= 50.0):
        raise ConfigError(f"{where} [mesh] size_mm must be \"auto\" or an element size in mm "
                          f"(0.5-50), got {size!r}")
    fit = cfg["fit"]
    if fit["method"] not in ("grid", "optimizer", "least_squares"):
        raise ConfigError(f"{where} [fit] method must be 'grid', 'optimizer' or "
                          f"'least_squares', got {fit['method']!r}")
    for path, spec in fit["parameters"].items():
        if not isinstance(spec, Mapping):
            raise ConfigError(f"{where} [fit.parameters] {path!r} must be a table "
                              "{min, max, step} or {values}")
        check_keys(spec, FIT_PARAMETER_KEYS, where=f"{where} [fit.parameters] {path!r}")
        if "values" not in spec and not {"min", "max"} <= set(spec):
            raise ConfigError(f"{where} [fit.parameters] {path!r} needs min and max "
                              "(and step for a grid) or values")
        try:
            get_param(cfg["model"], path)
        except KeyError as exc:
            raise ConfigError(f"{where} [fit.parameters]: {exc.args[0]}") from None
    sees = fit["sees"]
    if (not isinstance(sees, list) or not sees or len(set(sees)) != len(sees)
            or not set(sees) <= set(FIT_SEES)):
        raise ConfigError(f"{where} [fit] sees must be a non-empty list of distinct items "
                          f"from {list(FIT_SEES)}, got {sees!r}")
    if fit["enabled"] and not fit["parameters"]:
        raise ConfigError(f"{where} [fit] enabled = true needs [fit.parameters]")
    return cfg


def _check_register(table: Mapping, where: str) -> None:
    """The ``[register]`` table checked as the stage will, before any stage runs."""
    from breastmodel.pipeline.register import read_config

    try:
        read_config(table)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def _check_given_labels(seg: Mapping[str, Any], where: str) -> None:
    """``labels_positions`` names positions (a list of strings) whose label maps come from
    ``labels``, which it needs."""
    only = seg.get("labels_positions")
    if only is None:
        return
    if (not isinstance(only, list) or not only
            or not all(isinstance(p, str) and p for p in only)):
        raise ConfigError(f"{where} [segment] labels_positions must be a non-empty list of "
                          f"position names, got {only!r}")
    if not seg.get("labels"):
        raise ConfigError(f"{where} [segment] labels_positions needs labels (the folder of "
                          "<position>_labels.nii.gz)")


def given_labels(seg: Mapping[str, Any], position: str) -> Path | None:
    """The label map ``[segment]`` gives for ``position`` instead of segmenting it
    (``labels/<position>_labels.nii.gz``; every position, or those in
    ``labels_positions``), or None."""
    folder, only = seg.get("labels"), seg.get("labels_positions")
    if not folder or (only is not None and position not in only):
        return None
    return Path(folder) / f"{position}_labels.nii.gz"


def _number(value: Any, param, where: str) -> None:
    """Refuse a parameter value that is not a number or lies outside the parameter's bounds
    (the message gives its unit)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where} must be a number ({param.unit}), got {value!r}")
    try:
        param.check(value, where)
    except ValueError:
        raise ConfigError(f"{where} = {value} {param.unit} is outside [{param.lower}, "
                          f"{param.upper}] {param.unit}") from None


def _check_effect(key: str, table: Any, where: str, label: str) -> None:
    from mechanics.effects import EFFECTS, effect_name
    from mechanics.effects.gravity import Gravity

    name = effect_name(key)
    at = f"{where} [model.effects.{label}]"
    if name == Gravity.name:
        raise ConfigError(f"{at}: gravity is set per position by the pipeline; use "
                          "model.density and model.g")
    if name not in EFFECTS:
        raise ConfigError(f"{at}: unknown effect {name!r}; known: {sorted(EFFECTS)}")
    if not isinstance(table, Mapping):
        raise ConfigError(f"{at} must be a table")
    cls = EFFECTS[name]
    params = {p.name: p for p in cls.params}
    options = {o.name: o for o in cls.option_specs}
    for k, v in table.items():
        if k in params:
            _number(v, params[k], f"{at} {k}")
        elif k not in options:
            raise ConfigError(f"{at}: unknown key {k!r}; {name} takes "
                              f"{sorted(params) + sorted(options)}")
        elif options[k].types and not isinstance(v, options[k].types):
            raise ConfigError(f"{at} {k} must be of type "
                              f"{' or '.join(t.__name__ for t in options[k].types)}, "
                              f"got {v!r}")
        else:
            try:
                options[k].check(v, name)
            except ValueError as exc:
                raise ConfigError(f"{at} {k}: {exc}") from None


def check_model(model: Mapping[str, Any], *, where: str = "run config") -> None:
    """Validate a ``[model]`` table against the registries before any stage runs: regions,
    materials and their parameters (numbers within bounds), effects, their parameters and
    options (declared names, types and choices). Messages name ``where`` (the file), the
    table and the key.

    Raises
    ------
    ConfigError
        The first mistake found.
    """
    from mechanics.materials import MATERIALS
    from mechanics.mesh import REGIONS

    for region, mat in model["materials"].items():
        at = f"{where} [model.materials.{region}]"
        if region not in REGIONS:
            raise ConfigError(f"{where} [model.materials]: unknown region {region!r}; "
                              f"known: {sorted(REGIONS)}")
        if not isinstance(mat, Mapping) or "name" not in mat:
            raise ConfigError(f"{at} needs a 'name'")
        cls = MATERIALS.get(mat["name"])
        if cls is None:
            raise ConfigError(f"{at}: unknown material {mat['name']!r}; known: "
                              f"{sorted(MATERIALS)}")
        params = {p.name: p for p in cls.params}
        for k, v in mat.items():
            if k == "name":
                continue
            if k not in params:
                raise ConfigError(f"{at}: unknown key {k!r}; {mat['name']} takes "
                                  f"{sorted(params)}")
            _number(v, params[k], f"{at} {k}")
    for key, table in model["effects"].items():
        if not isinstance(table, list):
            _check_effect(key, table, where, key)
        for i, t in enumerate(table if isinstance(table, list) else []):
            _check_effect(key, t, where, f"{key} #{i + 1}")


def load_run_config(path: str | Path | None, *, drop: Sequence[str] = ()) -> dict:
    """Read and resolve a run config file (None: the defaults); ``drop``: top-level keys to
    ignore (a run folder's ``config.toml`` also records the ``subject``)."""
    if path is None:
        return resolve_config({})
    raw = load_toml(path, stage="run")
    for k in drop:
        raw.pop(k, None)
    return resolve_config(raw, where=f"run: {path}")


def _split(path: str) -> list[str]:
    parts = str(path).split(".")
    if len(parts) != 3 or parts[0] not in ("materials", "effects"):
        raise KeyError(f"parameter path {path!r} must be 'materials.<region>.<name>' or "
                       "'effects.<effect>.<name>'")
    return parts


def get_param(model: Mapping[str, Any], path: str) -> float | None:
    """Value of a parameter path in a model table (None when the effect keeps its default).

    A path may tie several parameters to one value: ``"materials.breast_left.E|
    materials.breast_right.E"`` (the value of the first is returned).

    Raises
    ------
    KeyError
        Malformed path, or a region / effect that the model does not have.
    """
    first, *rest = str(path).split("|")
    for other in rest:
        get_param(model, other)  # each tied path must exist
    kind, owner, name = _split(first)
    table = model[kind]
    if owner not in table:
        raise KeyError(f"parameter path {path!r}: the model has no {kind[:-1]} {owner!r} "
                       f"(has {sorted(table)})")
    return table[owner].get(name)


def set_params(model: Mapping[str, Any], params: Mapping[str, float]) -> dict:
    """A copy of the model table with parameter paths (``|``-tied allowed) set to values
    (input unchanged)."""
    out = copy.deepcopy(dict(model))
    for tied, value in params.items():
        for path in str(tied).split("|"):
            kind, owner, name = _split(path)
            if owner not in out[kind]:
                raise KeyError(f"parameter path {path!r}: the model has no {kind[:-1]} "
                               f"{owner!r}")
            out[kind][owner] = {**out[kind][owner], name: float(value)}
    return out


def materials_by_code(model: Mapping[str, Any], region_codes: Sequence[int]) -> dict[int, dict]:
    """Region code -> material dict for the regions a mesh has.

    Gland regions without their own material inherit their side's breast material.

    Raises
    ------
    ConfigError
        A mesh region without a material.
    """
    from mechanics.mesh import REGIONS

    names = {code: name for name, code in REGIONS.items()}
    mats = model["materials"]
    out = {}
    for code in sorted({int(c) for c in region_codes}):
        name = names.get(code, f"region_{code}")
        if name not in mats and name.startswith("gland_"):
            name = "breast_" + name.split("_", 1)[1]
        if name not in mats:
            raise ConfigError(f"model: the mesh has region {names.get(code, code)!r} but "
                              f"[model.materials] has no entry for it (has {sorted(mats)})")
        out[code] = dict(mats[name])
    return out
