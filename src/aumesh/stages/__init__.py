"""The DVC stages, one module each (``dvc.yaml``'s ``ingest``, ``prepare``, ``evaluate``, ``release``).

Each stage's ``main`` takes the configuration ``params.yaml`` holds (``aumesh <stage> --params params.yaml`` loads it),
removes what a killed earlier run left, calls the pipeline and writes the stage's outputs. Paths come from
``cfg.paths`` (relative to the stage's working directory, so a DVC queued experiment writes into its own temporary
copy); only MLflow goes to the workspace. The passes get those paths made absolute (``aumesh.core.io.absolute``: a
cluster's workers run in directories of their own); the outputs record them as given (``aumesh.core.io.recorded``).
Each stage imports only what it runs: a stage is a process of its own, and scikit-learn, MLflow, pandera or
matplotlib imported for nothing cost seconds of every ``dvc repro``.
"""
