"""``batch``: many models, one ``scale`` run each, on Dask (docs/BATCH.md): the job run for one
model in a worker (:mod:`.job`), whether a previous output can be kept (:mod:`.rerun`), the
threads each job may use (:mod:`.threads`) and the Dask execution (:mod:`.execute`). Re-exports
nothing.
"""
