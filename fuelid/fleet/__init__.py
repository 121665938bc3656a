"""The fleet service: trucks upload MCAP files, a registry keeps per-truck model versions, identification
jobs run on Dask (fleet.jobs), engineers fetch models and reports (`fuelid serve`, `upload`, `fetch`, `trucks`).

Modules: db (schema, migrations, queries), storage (content-addressed blobs, upload checks), auth (tokens and
roles), refits (identification jobs and their scheduling), app (the HTTP API), client (the engineer's client).
"""
