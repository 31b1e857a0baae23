"""Solving any tet mesh from a config, the library side of ``breastmodel simulate``
(:mod:`breastmodel.commands.simulate` documents the config and the files written)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("breastmodel.simulate")
#: Tables of a simulate config: run.toml's model and solver, and this solve's gravity.
_TOP_KEYS = ("model", "solver", "gravity")
_RUN_TABLES = ("model", "solver")
_GRAVITY_KEYS = ("direction", "regions", "density_by_region")
#: Tables of the former dialect, and those that only it has.
_FORMER_TOP_KEYS = ("materials", "supports", "gravity", "point_loads", "effects", "solver")
_FORMER_ONLY_KEYS = ("materials", "supports", "point_loads", "effects")


def solver_keys() -> tuple[str, ...]:
    """Keys of the former dialect's ``[solver]`` table: the fields of ``SolverOptions`` and
    ``formulation``."""
    from dataclasses import fields

    from mechanics.solver import SolverOptions

    return (*(f.name for f in fields(SolverOptions)), "formulation")


def cost_table(summary: dict[str, Any]) -> str:
    """Text table of a solve's costs per load step (wall / CPU seconds per phase, counts) and
    its threads and peak memory, from a ``solve.json`` summary."""
    phases = ("material", "effects", "assembly", "factor", "solve")
    head = (f"{'step':>4} {'load':>6} {'newton':>6} {'fact':>4} {'anal':>4} "
            + " ".join(f"{p:>13}" for p in phases) + "  (wall/cpu s)")
    rows = [head]
    for e in summary.get("log", []):
        cells = " ".join(f"{e.get(f't_{p}', 0.0):6.2f}/{e.get(f'cpu_{p}', 0.0):6.2f}"
                         for p in phases)
        rows.append(f"{e['step']:>4} {e['load']:6.3f} {e['newton']:>6} "
                    f"{e.get('factorizations', 0):>4} {e.get('analyses', 0):>4} {cells}"
                    + ("" if e.get("converged") else "  cut back"))
    st = summary.get("stats", {})
    if st:
        by_eff = ", ".join(f"{k} {v:.2f}" for k, v in st.get("cpu_by_effect", {}).items())
        rows.append(f"{st.get('linear_solver')} on {st.get('threads')} thread(s), "
                    f"{st.get('unknowns')} unknowns; peak memory {st.get('peak_rss_mb', 0):.0f} "
                    f"MB; effects CPU s: {by_eff or 'none'}")
    return "\n".join(rows)


@dataclass(frozen=True)
class SimulateInputs:
    """A validated simulate config: ``materials`` (region codes -> material dict, for the
    codes of a mesh), ``effects`` (name -> keywords, gravity included), solver ``options``,
    ``formulation`` and ``record`` (the config as written beside the results)."""

    materials: Callable[[np.ndarray], dict[int, dict]]
    effects: dict[str, Any]
    options: Any
    formulation: str
    record: dict[str, Any]


def simulate_inputs(config: Mapping[str, Any], *,
                    where: str = "simulate config") -> SimulateInputs:
    """Validate a simulate config: ``[model]`` and ``[solver]`` as ``run.toml``'s
    (:func:`breastmodel.pipeline.config.resolve_config`: defaults, bounds, messages naming
    ``where``, the table and the key) and the optional ``[gravity]`` load case. A config in
    the former dialect (materials keyed by region code) is read as before, with a
    FutureWarning.

    Raises
    ------
    ConfigError
        Unknown table or key, or a bad model, solver or gravity table.
    """
    from breastmodel.config import ConfigError, check_keys
    from breastmodel.pipeline.config import materials_by_code, resolve_config
    from breastmodel.pipeline.problem import solver_options

    if "model" not in config and any(k in config for k in _FORMER_ONLY_KEYS):
        return _former_inputs(config, where=where)
    check_keys(config, _TOP_KEYS, where=where)
    for name, table in config.items():
        if not isinstance(table, Mapping):
            raise ConfigError(f"{where}: [{name}] must be a table")
    cfg = resolve_config({k: v for k, v in config.items() if k in _RUN_TABLES}, where=where)
    model = cfg["model"]
    record = {"model": model, "solver": cfg["solver"]}
    effects = dict(model["effects"])
    if "gravity" in config:
        gravity = dict(config["gravity"])
        check_keys(gravity, _GRAVITY_KEYS, where=f"{where} [gravity]")
        if "direction" not in gravity:
            raise ConfigError(f"{where} [gravity] needs a 'direction'")
        record["gravity"] = gravity
        effects["gravity"] = {**gravity, "density": float(model["density"]),
                              "g": float(model["g"])}
    return SimulateInputs(lambda region: materials_by_code(model, np.unique(region)), effects,
                          solver_options(cfg["solver"]), model["formulation"], record)


def model_inputs(config: dict[str, Any], *, where: str = "simulate config"):
    """(materials, effects, solver options, formulation) from a config dict in the former
    dialect (materials keyed by region code)."""
    from breastmodel.config import ConfigError, check_keys
    from mechanics.solver import SolverOptions

    check_keys(config, _FORMER_TOP_KEYS, where=where)
    mats_cfg = config.get("materials")
    if not mats_cfg:
        raise ConfigError(f"{where}: [materials.<region>] is required")
    materials = {}
    for key, m in mats_cfg.items():
        try:
            code = int(key)
        except ValueError:
            raise ConfigError(f"{where}: materials keys are region codes, got {key!r}") from None
        if not isinstance(m, dict) or "name" not in m:
            raise ConfigError(f"{where}: [materials.{key}] needs a 'name'")
        materials[code] = dict(m)
    effects: dict[str, Any] = {}
    supports = config.get("supports", [])
    for i, s in enumerate(supports):
        check_keys(s, ("node_set", "components", "values"), where=f"{where} [[supports]] #{i}")
        effects[f"fixed:{i}"] = dict(s)
    if "gravity" in config:
        check_keys(config["gravity"], ("direction", "density", "g", "regions",
                                       "density_by_region"), where=f"{where} [gravity]")
        effects["gravity"] = dict(config["gravity"])
    for i, pl in enumerate(config.get("point_loads", [])):
        check_keys(pl, ("node_set", "force"), where=f"{where} [[point_loads]] #{i}")
        effects[f"point_load:{i}"] = dict(pl)
    for name, kw in config.get("effects", {}).items():
        effects[name] = dict(kw)
    solver_cfg = dict(config.get("solver", {}))
    check_keys(solver_cfg, solver_keys(), where=f"{where} [solver]")
    formulation = solver_cfg.pop("formulation", "anp")
    return materials, effects, SolverOptions(**solver_cfg), formulation


def _former_inputs(config: Mapping[str, Any], *, where: str) -> SimulateInputs:
    """:class:`SimulateInputs` of a former-dialect config, with a FutureWarning."""
    import warnings

    warnings.warn(f"{where}: [materials.<region code>], [[supports]], [[point_loads]] and "
                  "[effects.NAME] are deprecated; write run.toml's tables instead: "
                  "[model.materials.<region name>], [model.effects.fixed] (supports), "
                  "[model.effects.point_load], [model.effects.NAME], density and g in "
                  "[model], formulation in [model], [gravity] direction",
                  FutureWarning, stacklevel=3)
    materials, effects, options, formulation = model_inputs(dict(config), where=where)
    return SimulateInputs(lambda region: materials, effects, options, formulation,
                          dict(config))


def simulate_file(mesh_path: Path, config: dict[str, Any], out: Path, *,
                  config_path: Path | None = None) -> dict[str, Any]:
    """Solve ``mesh_path`` with ``config``; write result.vtu, solve.json, provenance."""
    from breastmodel.config import write_json, write_provenance
    from mechanics.export import result_fields
    from mechanics.model import build_model
    from mechanics.solver import SolverError, solve
    from meshing.export import read_vtu, write_vtu

    where = f"simulate config {config_path}" if config_path else "simulate config"
    inputs = simulate_inputs(config, where=where)
    mesh = read_vtu(mesh_path)
    try:
        model = build_model(mesh, inputs.materials(mesh.region), inputs.effects,
                            formulation=inputs.formulation)
    except ValueError as exc:
        raise ValueError(f"simulate [{mesh_path}]: {exc}") from None
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, inputs.record, command=f"simulate {mesh_path}")
    t0 = time.perf_counter()
    error = None
    try:
        state = solve(model, options=inputs.options)
    except SolverError as exc:
        state, error = exc.state, exc
    summary = {
        "mesh": str(mesh_path), "n_nodes": mesh.n_nodes, "n_tets": mesh.n_tets,
        "converged": bool(state is not None and state.converged),
        "load_reached": float(state.load) if state is not None else 0.0,
        "load_steps": state.load_steps if state is not None else 0,
        "newton_iterations": state.newton_iterations if state is not None else 0,
        "wall_time_s": time.perf_counter() - t0,
        "max_displacement_mm": state.max_displacement() if state is not None else 0.0,
        "error": None if error is None else str(error),
        "stats": dict(state.stats) if state is not None else {},
        "log": [dict(e) for e in state.log] if state is not None else [],
    }
    if state is not None:
        pts, fields, cell_fields = result_fields(mesh, state)
        write_vtu(out / "result.vtu", mesh, points=pts, fields=fields,
                  cell_fields=cell_fields)
    write_json(out / "solve.json", summary)
    if error is not None:
        raise RuntimeError(f"simulate [{mesh_path}]: {error} (last converged state written to "
                           f"{out / 'result.vtu'})")
    return summary
#: Model of the demo: run.toml's default materials (breast regions Neo-Hookean 1 kPa, muscle
#: 10 kPa, nu 0.49; gland inherits its side's breast) and supports (node set "fixed"), solved
#: with ``SolverOptions``' defaults.
DEMO_CONFIG = {
    "model": {
        "materials": {
            name: {"name": "neo_hookean", "E": 10.0 if name == "muscle" else 1.0, "nu": 0.49}
            for name in ("breast_left", "muscle", "breast_right")
        },
        "effects": {"fixed": {"node_set": "fixed"}},
    },
    "solver": {"tol": 1e-8, "max_newton": 20, "initial_steps": 1, "max_cutbacks": 20},
}


def simulate_positions(mesh_path: Path, reg_dir: Path, out: Path,
                       config: dict[str, Any] | None = None) -> dict[str, Any]:
    """Simulate every position of ``reg_dir/gravity.json`` (name -> gravity unit vector in
    the mesh frame) on one mesh; writes OUT/<position>/ and OUT/summary.json."""
    import json

    from breastmodel.config import write_json

    gravity = json.loads((Path(reg_dir) / "gravity.json").read_text())
    base = dict(config or DEMO_CONFIG)
    # The former dialect carries density and g in [gravity]; the new one in [model].
    former = "model" not in base and any(k in base for k in _FORMER_ONLY_KEYS)
    water = {"density": 1000.0, "g": 9.81} if former else {}
    summary = {}
    for name, direction in gravity.items():
        cfg = {**base, "gravity": {"direction": list(direction), **water}}
        s = simulate_file(Path(mesh_path), cfg, Path(out) / name)
        summary[name] = {k: s[k] for k in ("converged", "max_displacement_mm",
                                           "newton_iterations", "wall_time_s", "load_steps")}
        log.info("%s: max displacement %.2f mm", name, s["max_displacement_mm"])
    write_json(Path(out) / "summary.json", summary)
    return summary
