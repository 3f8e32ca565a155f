"""rotonly: rotation-only SfM stage (TRRM / GRRM, Li, Cai, Wu: "Towards Rotation-only Imaging Geometry").

``rotonly_cli.run(INPUT, ...)`` runs the whole chain in memory (rotonly_cli/api.py); the
two-view and multi-view building blocks are ``rotonly_cli.twoview`` and ``rotonly_cli.multiview``.
"""

from rotonly_cli.version import __version__

__all__ = ["run", "__version__"]


def __getattr__(name: str):
    # imported on first use: the console script imports this package and needs none of it
    if name == "run":
        from rotonly_cli.api import run

        return run
    raise AttributeError(f"module 'rotonly_cli' has no attribute {name!r}")
