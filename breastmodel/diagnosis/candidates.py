"""Candidate missing effects: every registered effect a model does not use, and every
parameter it holds fixed, as a change of the ``[model]`` table.

A :class:`Candidate` is plain data: the effect tables it adds, replaces or removes, the
parameters that are re-fitted with it (bounds from the effect's declared :class:`Param`), and
how its switch-on may be scaled in the linear prediction (``amplitude``: ``(1, 1)`` for an
on/off change such as sliding, ``(0, 2)`` where the effect's strength is continuous).
Enumerating from :data:`mechanics.effects.EFFECTS` means a new effect file is a new
candidate with no edit here, unless it needs a probe setting other than its defaults.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

__all__ = ["Candidate", "add_to_config", "candidate_by_name", "enumerate_candidates"]

#: Effects that are not tissue physics to diagnose, with the reason.
NOT_CANDIDATES = {
    "gravity": "set per position from the registration",
    "point_load": "an external load, not a property of the subject",
    "fixed": "the chest-wall boundary condition every model has",
}
#: Effect parameters that are numerical settings, not physics (never scored).
NUMERICAL = {"penalty", "tangential_penalty", "smoothing", "pressure_smoothing"}
#: Effects whose own strength is probed at a value other than the registry default, because
#: the default is the "barely on" end (Jm = 10 is nearly Neo-Hookean at breast strains).
PROBE = {"strain_stiffening": {"Jm": 0.3}}
#: Gent limit used to probe a membrane's strain stiffening.
MEMBRANE_JM_PROBE = 0.5


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


def _used(model: Mapping[str, Any]) -> dict[str, dict]:
    """Effect name -> table of the effects a model uses (first instance of each)."""
    out: dict[str, dict] = {}
    for key, table in model["effects"].items():
        out.setdefault(str(key).split(":", 1)[0], dict(table) if isinstance(table, Mapping)
                       else {})
    return out


def _key(model: Mapping[str, Any], name: str) -> str:
    return next(k for k in model["effects"] if str(k).split(":", 1)[0] == name)


def enumerate_candidates(model: Mapping[str, Any], fitted: set[str] | frozenset = frozenset(),
                         *, regions: set[int] | None = None, node_pairs: set[str] | None = None,
                         ) -> tuple[list[Candidate], list[dict]]:
    """Every candidate change of ``model`` (a resolved ``[model]`` table).

    Parameters
    ----------
    model : the model the run used (fitted values included)
    fitted : parameter paths the fit varies (they are not "held fixed"; ``|``-tied paths are
        split)
    regions : region codes of the mesh (gland candidates need gland regions)
    node_pairs : node-pair set names of the mesh (ligament groups need theirs)

    Returns
    -------
    candidates : list of Candidate
    skipped : [{"name", "reason"}] what is deliberately not scored, and why
    """
    from mechanics.effects import EFFECTS
    from mechanics.effects.ligaments import GROUPS
    from mechanics.materials import MATERIALS
    from mechanics.mesh import REGIONS

    fitted = {p for f in fitted for p in str(f).split("|")}
    used = _used(model)
    out: list[Candidate] = []
    skipped: list[dict] = []
    for name, cls in sorted(EFFECTS.items()):
        if name in NOT_CANDIDATES:
            skipped.append({"name": name, "reason": NOT_CANDIDATES[name]})
            continue
        if name in used:
            continue
        strength = {p.name: p for p in cls.params if p.name not in NUMERICAL}
        main = next(iter(strength.values()), None)
        if name == "tied":
            if "sliding" in used:
                out.append(Candidate("tied", "effect", "bonded breast-muscle interface instead "
                                     "of sliding", {_key(model, "sliding"): None, "tied": {}}))
            else:
                skipped.append({"name": "tied", "reason": "the model's interface is already "
                                "bonded (conforming mesh)"})
            continue
        if name == "sliding":
            change: dict[str, Any] = {"sliding": {}}
            if "tied" in used:
                change[_key(model, "tied")] = None
            out.append(Candidate("sliding", "effect", cls.doc or "sliding interface", change))
            continue
        if name == "ligaments":
            have = sorted(node_pairs) if node_pairs is not None else [
                f"ligament_{g}" for g in GROUPS]
            for g in GROUPS:
                if f"ligament_{g}" in have:
                    out.append(Candidate(
                        f"ligaments:{g}", "effect", f"{g} suspensory ligaments (tension-only)",
                        {"ligaments": {"groups": [g]}},
                        {"effects.ligaments.E": _bounds(main)}, (0.0, 2.0),
                        start={"effects.ligaments.E": main.default}))
            continue
        if name == "regions":
            E = [float(model["materials"].get(f"breast_{s}", {}).get("E", 1.0))
                 for s in ("left", "right")]
            lo, hi = _bounds(strength["E_left"])
            E = [min(max(e, lo), hi) for e in E]
            replaces = tuple(f"materials.breast_{s}.E" for s in ("left", "right"))
            out.append(Candidate(
                "regions:asymmetry", "effect", "different moduli of the left and right breast",
                {"regions": {"E_left": E[0], "E_right": E[1], "gland": False}},
                {"effects.regions.E_left": (lo, hi), "effects.regions.E_right": (lo, hi)},
                (0.0, 0.0), replaces,
                {"effects.regions.E_left": E[0], "effects.regions.E_right": E[1]}))
            if regions is None or {REGIONS["gland_left"], REGIONS["gland_right"]} & regions:
                out.append(Candidate(
                    "regions:gland", "effect", "glandular tissue with its own modulus",
                    {"regions": {"E_left": E[0], "E_right": E[1], "E_gland": float(E[0]),
                                 "gland": True}},
                    {"effects.regions.E_gland": _bounds(strength["E_gland"])}, (0.0, 0.0),
                    replaces, {"effects.regions.E_gland": float(E[0])}))
            else:
                skipped.append({"name": "regions:gland", "reason": "the mesh has no gland "
                                "regions ([mesh] keep_gland = true)"})
            continue
        probe = dict(PROBE.get(name, {}))
        free, start = {}, {}
        if main is not None:
            pname = next(iter(probe), main.name)
            path = f"effects.{name}.{pname}"
            free = {path: _bounds(strength[pname])}
            v = float(probe.get(pname, strength[pname].default))
            start = {path: v if v > 0 else strength[pname].upper / 100}  # log-scale re-fit
        out.append(Candidate(name, "effect", cls.doc or name, {name: probe}, free,
                             (0.0, 2.0) if free else (1.0, 1.0), start=start))
    # Options of effects the model already uses: a membrane's strain stiffening, missing
    # ligament groups.
    for name in ("skin", "fascia"):
        if name in used and used[name].get("law", "neo_hookean") != "gent":
            key = _key(model, name)
            out.append(Candidate(
                f"strain_stiffening:{name}", "option",
                f"Gent strain stiffening of the {name} membrane",
                {key: {**used[name], "law": "gent", "Jm": MEMBRANE_JM_PROBE}},
                {f"effects.{key}.Jm": _bounds(EFFECTS[name].params[-1])}, (0.0, 2.0),
                start={f"effects.{key}.Jm": MEMBRANE_JM_PROBE}))
    if "ligaments" in used and node_pairs is not None:
        have = set(used["ligaments"].get("groups") or [
            g for g in GROUPS if f"ligament_{g}" in node_pairs])
        key = _key(model, "ligaments")
        for g in GROUPS:
            if g not in have and f"ligament_{g}" in node_pairs:
                out.append(Candidate(
                    f"ligaments:{g}", "option", f"{g} suspensory ligaments (tension-only)",
                    {key: {**used["ligaments"], "groups": sorted(have | {g})}}))
    # Parameters held fixed.
    for name, table in used.items():
        if name in NOT_CANDIDATES or name not in EFFECTS:
            continue
        key = _key(model, name)
        for p in EFFECTS[name].params:
            path = f"effects.{key}.{p.name}"
            if path in fitted:
                continue
            if p.name in NUMERICAL:
                skipped.append({"name": f"parameter:{path}", "reason": "a numerical setting"})
            elif p.name == "Jm" and table.get("law", "neo_hookean") != "gent" and name in (
                    "skin", "fascia"):
                continue  # inert under the Neo-Hookean law; the strain-stiffening option covers it
            elif p.name == "thickness":
                skipped.append({"name": f"parameter:{path}", "reason": "membrane stiffness "
                                "depends on E x thickness; E is scored"})
            elif name == "regions" or name == "ligaments" and p.name == "area":
                skipped.append({"name": f"parameter:{path}", "reason": "covered by E"
                                if p.name == "area" else "scored through its E parameters"})
            else:
                cand = _parameter(path, table.get(p.name, p.default), _bounds(p), p)
                if float(table.get(p.name, p.default)) <= 0:  # switched off (e.g. friction 0)
                    cand = replace(cand, effects={key: {**table, p.name: cand.start[path]}},
                                   amplitude=(0.0, 1.0))
                out.append(cand)
    for region, mat in model["materials"].items():
        cls = MATERIALS.get(mat.get("name"))
        for p in getattr(cls, "params", ()):
            path = f"materials.{region}.{p.name}"
            if path in fitted or p.name == "nu":
                continue
            if "regions" in used and region.startswith(("breast_", "gland_")) and p.name == "E":
                continue  # the regions effect sets these moduli
            lo, hi = _bounds(p)
            v = float(mat.get(p.name, p.default))
            out.append(_parameter(path, v, (max(lo, v / 20), min(hi, v * 20)), p))
    skipped.append({"name": "materials.*.nu", "reason": "nearly incompressible tissue by design "
                    "(0.49, the paper's value)"})
    return out, skipped


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
