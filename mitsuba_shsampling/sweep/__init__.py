"""``sweep``: many ``compare`` jobs over a grid of scenes x maps x samplers, on a Dask cluster.

Data flows one way: grid file (:mod:`.grid`) -> cells with content keys and the per-cell
``compare`` job (:mod:`.cells`) -> Dask orchestration (:mod:`.run`) -> stored cell
folders (:mod:`.store`) -> the aggregate report (:mod:`.aggregate`). The command line is
in :mod:`.command`; see ``docs/SWEEP.md``.
"""
