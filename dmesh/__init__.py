"""DMesh: a differentiable representation for general triangle meshes (CPU-first re-implementation).

The library never imports the harness packages (`baselines`, `datasets`, `eval`).
"""

__version__ = "0.1.0"
