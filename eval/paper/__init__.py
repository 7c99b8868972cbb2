"""The paper's experiments: ``symbio eval table`` (Tables II-VI, ``table``), the baselines it compares
(``baselines``), rank statistics and critical-difference diagrams (``stats``) and config sweeps (``sweep``),
run as Dask jobs."""
