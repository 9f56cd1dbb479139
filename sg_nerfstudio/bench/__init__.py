"""sg-bench: the in-the-wild benchmark (layout, runs, tables). See `sg_nerfstudio.scripts.bench`."""
