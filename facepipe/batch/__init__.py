"""``facepipe batch``: many takes replayed and exported against one model on a Dask cluster
(jobs.py: the tasks, the skip check, batch.json; cluster.py: which cluster). It sits above
:mod:`facepipe.export`, which every take's task runs after its replay."""
