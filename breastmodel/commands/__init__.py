"""One module per CLI command. Each defines ``add_parser(subparsers)`` and ``run(args) -> int``.

Command modules import heavy libraries inside ``run`` so that ``--help`` stays fast.
"""

#: Order in which commands appear in ``breastmodel --help``.
COMMANDS = (
    "demo",
    "phantom",
    "info",
    "segment",
    "register",
    "mesh",
    "surface",
    "simulate",
    "effects",
    "run",
    "fit",
    "sweep",
    "diagnose",
    "compare",
)
