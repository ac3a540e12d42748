"""What a pipeline keeps on disk and where (SPEC §9): Zarr stores of trajectories and scores and
fitted-detector files (`store`), their paths in a project (`layout`), files written whole
(`fileio`) and YAML in and out (`yamlio`)."""
