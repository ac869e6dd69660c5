"""DMesh: a differentiable representation for general triangle meshes (CPU-first re-implementation).

Public entry points: `dmesh.DMesh`, `dmesh.wdt` (triangulation, power diagram), `dmesh.probability`
(face existence probabilities). The library never imports the harness packages (`baselines`,
`datasets`, `eval`).
"""

__version__ = "0.1.0"


def __getattr__(name):  # lazy: `import dmesh` stays cheap
    if name == "DMesh":
        from dmesh.model import DMesh

        return DMesh
    raise AttributeError(f"module 'dmesh' has no attribute {name!r}")
