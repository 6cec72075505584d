"""The application layer: PATH arguments -> recordings (each with its rig) -> frames -> results.

``sources`` (PATHs, recordings, rigs) -> ``frames`` (pixels, lazily) -> ``pipeline`` (method
dispatch, batching, failure isolation) -> ``run`` (the results CSV via ``results``, overlays,
summary; ``resume``), plus ``smoothing``, ``plots``, ``demo`` and the ``cli*`` modules. No
science here: the estimators live in ``sinkjax.soft`` and ``sinkjax.classic``.
"""
