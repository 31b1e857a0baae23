"""``breastmodel simulate MESH.vtu --config sim.toml --out DIR``: solve any tet mesh.

The mesh is a VTU with cell data ``region`` (int, the codes of ``mechanics.mesh.REGIONS``)
and one 0/1 point-data array per named node set. The config (TOML) holds ``run.toml``'s
``[model]`` and ``[solver]`` tables (same keys, defaults and validation; see
``examples/run.toml``) and the one load case of this solve::

    [model]
    formulation = "anp"        # "anp" (locking-free) | "standard"
    density = 1000.0           # kg/m^3
    g = 9.81                   # m/s^2

    [model.materials.breast_left]   # region name -> material (name + parameters); listing
    name = "neo_hookean"            # materials replaces the defaults (breasts 1 kPa, muscle
    E = 1.0                         # 10 kPa, nu 0.49); gland regions inherit their side's
    nu = 0.49                       # breast material

    [model.effects.fixed]      # any registered effect by name, with its keywords; listing
    node_set = "fixed"         # effects replaces the default (node set "fixed" held);
                               # several: [[model.effects.point_load]] node_set, force (mN)

    [gravity]                  # optional: this solve's gravity (density and g from [model])
    direction = [0, 0, -1]     # unit vector in the mesh frame

    [solver]                   # optional; run.toml's defaults: tol 1e-6, max_newton 25,
    linear_solver = "auto"     # initial_steps 2, max_cutbacks 12; "auto" | "scipy" |
    threads = 4                # "pardiso"; threads: PARDISO's (default env
                               # BREASTMODEL_THREADS, else the cores this process may use)

The former dialect (``[materials.<region code>]``, ``[[supports]]``, ``[gravity]`` with
density and g, ``[[point_loads]]``, ``[effects.NAME]``, ``formulation`` in ``[solver]``) is
still read, with a FutureWarning naming the new form.

DIR receives ``result.vtu`` (point data ``displacement`` in mm, cell data stress, J,
stretch), ``solve.json`` (converged, load reached, load steps, Newton iterations, wall time,
maximum displacement, ``stats``: threads, time per phase, counts of factorisations and
analyses, peak memory; ``log``: the same per load step, with each effect's CPU time) and the
resolved config with package versions.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from breastmodel.simulate import cost_table, simulate_file


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "simulate",
        help="solve a tet mesh under gravity and supports (hyperelastic FE)",
        description=(
            "Solve the static equilibrium of a tetrahedral mesh (VTU with cell data 'region' "
            "and 0/1 point data per node set) with the materials, supports and loads of a "
            "TOML config. Writes DIR/result.vtu and DIR/solve.json."
        ),
    )
    p.add_argument("mesh", type=Path, help="input mesh (.vtu, meshio-readable)")
    p.add_argument("--config", type=Path, required=True, help="simulation config (TOML)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.config import load_toml

    config = load_toml(args.config, stage="simulate")
    summary = simulate_file(args.mesh, config, args.out, config_path=args.config)
    print(f"simulate: {'converged' if summary['converged'] else 'NOT converged'}; "
          f"max displacement {summary['max_displacement_mm']:.3f} mm, "
          f"{summary['newton_iterations']} Newton iterations in {summary['load_steps']} load "
          f"step(s), {summary['wall_time_s']:.2f} s -> {args.out}")
    print(cost_table(summary))
    return 0
