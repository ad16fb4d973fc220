"""The stages' computation: the data passes (prepare, evaluate) on the compute engine, ingest, the release record."""
