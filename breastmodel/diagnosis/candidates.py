"""Candidate missing effects: every registered effect a model does not use, and every
parameter it holds fixed, as a change of the ``[model]`` table.

A :class:`Candidate` is plain data: the effect tables it adds, replaces or removes, the
parameters that are re-fitted with it (bounds from the effect's declared :class:`Param`), and
how its switch-on may be scaled in the linear prediction (``amplitude``: ``(1, 1)`` for an
on/off change such as sliding, ``(0, 2)`` where the effect's strength is continuous).
Candidates come from what each effect in :data:`mechanics.effects.EFFECTS` declares
(:class:`mechanics.effects.Effect`: ``not_diagnosed``, ``variants``, ``option_variants``,
``inert_params``, ``sets_materials`` and each parameter's ``numerical`` and ``unscored``), so
a new effect file is a new candidate with no edit here.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

__all__ = ["Candidate", "add_to_config", "candidate_by_name", "enumerate_candidates"]


@dataclass(frozen=True)
class Candidate:
    """One change of the model that the diagnosis scores.

    name : "skin", "ligaments:medial", "strain_stiffening:fascia", "parameter:effects.skin.E"
    kind : "effect" (a registered effect switched on), "option" (a law or group of an effect
        already used) or "parameter" (a parameter the model holds fixed)
    doc : one line for people
    effects : {effect key: table, or None to remove} applied to ``model["effects"]``
    free : {parameter path: (lower, upper)} re-fitted with the candidate
    amplitude : bounds of the switch-on's linear amount ((0, 0) when nothing is switched)
    replaces : fitted parameter paths that the candidate makes inert (dropped on refit)
    start : {parameter path: value} where the candidate's free parameters start
    measurement : "" for a change of the model; "rigid" or "offset" for an error of the
        measured skin, whose linear columns need no model evaluation
        (:mod:`breastmodel.diagnosis.measurement`)
    acts_on : positions a measurement candidate changes (empty: every position)
    """

    name: str
    kind: str
    doc: str
    effects: Mapping[str, Any] = field(default_factory=dict)
    free: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    amplitude: tuple[float, float] = (1.0, 1.0)
    replaces: tuple[str, ...] = ()
    start: Mapping[str, float] = field(default_factory=dict)
    measurement: str = ""
    acts_on: tuple[str, ...] = ()

    def apply(self, model: Mapping[str, Any]) -> dict:
        """A copy of the ``[model]`` table with this candidate switched on."""
        out = copy.deepcopy(dict(model))
        effects = dict(out["effects"])
        for key, table in self.effects.items():
            if table is None:
                effects.pop(key, None)
            else:
                effects[key] = copy.deepcopy(dict(table))
        out["effects"] = effects
        return out

    def to_dict(self) -> dict:
        return {"name": self.name, "kind": self.kind, "doc": self.doc,
                "effects": dict(self.effects), "free": {k: list(v) for k, v in self.free.items()},
                "amplitude": list(self.amplitude), "replaces": list(self.replaces),
                "start": dict(self.start), "measurement": self.measurement,
                "acts_on": list(self.acts_on)}


def _bounds(param) -> tuple[float, float]:
    return (float(param.lower), float(param.upper))


def _view(model: Mapping[str, Any], regions, node_pairs, node_sets=None):
    """The :class:`mechanics.effects.ModelView` of a model: the first instance of each
    effect it uses (name -> table, name -> key), its materials and what the mesh has."""
    from mechanics.effects import ModelView

    used: dict[str, dict] = {}
    keys: dict[str, str] = {}
    for key, table in model["effects"].items():
        name = str(key).split(":", 1)[0]
        if name not in used:
            used[name] = dict(table) if isinstance(table, Mapping) else {}
            keys[name] = key
    return ModelView(used, keys, dict(model.get("materials", {})),
                     None if regions is None else frozenset(regions),
                     None if node_pairs is None else frozenset(node_pairs),
                     None if node_sets is None else frozenset(node_sets))


def _from_variant(v) -> Candidate:
    return Candidate(v.name, v.kind, v.doc, v.effects, v.free, v.amplitude, v.replaces, v.start)


def _add_variants(variants, out: list[Candidate], skipped: list[dict]) -> None:
    for v in variants:
        if v.skip:
            skipped.append({"name": v.name, "reason": v.skip})
        else:
            out.append(_from_variant(v))


def enumerate_candidates(model: Mapping[str, Any], fitted: set[str] | frozenset = frozenset(),
                         *, regions: set[int] | None = None, node_pairs: set[str] | None = None,
                         node_sets: set[str] | None = None,
                         ) -> tuple[list[Candidate], list[dict]]:
    """Every candidate change of ``model`` (a resolved ``[model]`` table).

    Parameters
    ----------
    model : the model the run used (fitted values included)
    fitted : parameter paths the fit varies (they are not "held fixed"; ``|``-tied paths are
        split)
    regions : region codes of the mesh (gland candidates need gland regions)
    node_pairs : node-pair set names of the mesh (ligament groups need theirs)
    node_sets : names of the mesh's node sets that hold nodes (the scan's cut needs its own)

    Returns
    -------
    candidates : list of Candidate
    skipped : [{"name", "reason"}] what is deliberately not scored, and why
    """
    from mechanics.effects import EFFECTS

    fitted = {p for f in fitted for p in str(f).split("|")}
    view = _view(model, regions, node_pairs, node_sets)
    out: list[Candidate] = []
    skipped: list[dict] = []
    # Effects the model does not use.
    for name, cls in sorted(EFFECTS.items()):
        if cls.not_diagnosed:
            skipped.append({"name": name, "reason": cls.not_diagnosed})
        elif name not in view.used:
            _add_variants(cls.variants(view), out, skipped)
    # Options of effects the model already uses (a membrane's law, missing ligament groups).
    for name, table in view.used.items():
        if name in EFFECTS and not EFFECTS[name].not_diagnosed:
            _add_variants(EFFECTS[name].option_variants(view.keys[name], table, view), out,
                          skipped)
    out += _held_fixed(model, view, fitted, skipped)
    skipped.append({"name": "materials.*.nu", "reason": "nearly incompressible tissue by design "
                    "(0.49, the paper's value)"})
    return out, skipped


def _held_fixed(model: Mapping[str, Any], view, fitted: set[str],
                skipped: list[dict]) -> list[Candidate]:
    """Candidates re-fitting a parameter the model holds fixed: effect parameters (unless
    numerical, inert or declared unscored) and material parameters (unless an effect used
    sets them)."""
    from mechanics.effects import EFFECTS
    from mechanics.materials import MATERIALS

    out: list[Candidate] = []
    for name, table in view.used.items():
        cls = EFFECTS.get(name)
        if cls is None or cls.not_diagnosed:
            continue
        key = view.keys[name]
        inert = cls.inert_params(table)
        for p in cls.params:
            path = f"effects.{key}.{p.name}"
            if path in fitted or p.name in inert and not p.numerical:
                continue
            if p.numerical:
                skipped.append({"name": f"parameter:{path}", "reason": "a numerical setting"})
            elif p.unscored:
                skipped.append({"name": f"parameter:{path}", "reason": p.unscored})
            else:
                cand = _parameter(path, table.get(p.name, p.default), _bounds(p), p)
                if float(table.get(p.name, p.default)) <= 0:  # switched off (e.g. friction 0)
                    cand = replace(cand, effects={key: {**table, p.name: cand.start[path]}},
                                   amplitude=(0.0, 1.0))
                out.append(cand)
    overridden = {s for n in view.used if n in EFFECTS for s in EFFECTS[n].sets_materials}
    for region, mat in model["materials"].items():
        cls = MATERIALS.get(mat.get("name"))
        for p in getattr(cls, "params", ()):
            path = f"materials.{region}.{p.name}"
            if path in fitted or p.name == "nu" or f"{region}.{p.name}" in overridden:
                continue
            lo, hi = _bounds(p)
            v = float(mat.get(p.name, p.default))
            out.append(_parameter(path, v, (max(lo, v / 20), min(hi, v * 20)), p))
    return out


def _parameter(path: str, value: float, bounds: tuple[float, float], p) -> Candidate:
    """A parameter held fixed, re-fitted in log scale: a value of 0 (e.g. no friction) is
    probed from the parameter's default, and a lower bound of 0 becomes 1/1000 of the start."""
    start = float(value) if value > 0 else float(p.default if p.default > 0 else p.upper / 100)
    lo, hi = bounds
    lo = lo if lo > 0 else min(start, hi) * 1e-3
    return Candidate(f"parameter:{path}", "parameter",
                     f"{p.doc or p.name} ({p.unit}), held at {value:g}", {},
                     {path: (lo, hi)}, (0.0, 0.0), start={path: start})


def candidate_by_name(model: Mapping[str, Any], name: str, **mesh_info) -> Candidate:
    """The candidate called ``name`` for this model.

    Raises
    ------
    ValueError
        No such candidate; the message lists the known ones.
    """
    cands, _ = enumerate_candidates(model, **mesh_info)
    for c in cands:
        if c.name == name:
            return c
    raise ValueError(f"--add-effect: {name!r} is not a candidate for this model; "
                     f"candidates: {', '.join(c.name for c in cands)}")


def add_to_config(cfg: Mapping[str, Any], cand: Candidate, *,
                  start: Mapping[str, float] | None = None) -> dict:
    """A run config with ``cand`` switched on and its parameters added to the fit.

    Parameters
    ----------
    cfg : resolved run config
    cand : the candidate
    start : parameter path -> value to start the candidate's parameters from (e.g. the
        diagnosis' estimate), clipped to the bounds

    The fitted parameters the candidate makes inert (``replaces``) leave the fit; the fit is
    switched on when the candidate has parameters to fit.
    """
    from breastmodel.pipeline.config import resolve_config, set_params

    out = copy.deepcopy(dict(cfg))
    out["model"] = set_params(cand.apply(out["model"]), cand.start)
    params = {p: s for p, s in out["fit"]["parameters"].items()
              if not set(str(p).split("|")) & set(cand.replaces)}
    for path, (lo, hi) in cand.free.items():
        params[path] = {"min": lo, "max": hi}
    out["fit"] = {**out["fit"], "parameters": params, "enabled": bool(params)}
    if start:
        vals = {p: min(max(float(v), cand.free[p][0]), cand.free[p][1])
                for p, v in start.items() if p in cand.free and math.isfinite(v)}
        out["model"] = set_params(out["model"], vals)
    return resolve_config(out, where=f"--add-effect {cand.name}")
