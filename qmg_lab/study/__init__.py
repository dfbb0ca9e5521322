"""Design studies: many simulated campaigns over a grid of configurations, on Dask."""
