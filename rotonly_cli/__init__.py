"""rotonly: rotation-only SfM stage (TRRM / GRRM, Li, Cai, Wu: "Towards Rotation-only Imaging Geometry")."""

__version__ = "0.1.0"
