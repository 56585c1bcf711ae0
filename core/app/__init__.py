"""What runs the core: `FitSettings`, `GenerativeShapeModel` and `fit_meshes` (the
pipeline), which stages run and which earlier output is reused, the `shapegen` command,
background jobs and their worker process, and gated sampling on a Dask cluster."""
