"""The files of the evaluate stage's output folder (``paths.model_dir``, ``build/model/``), named in one place."""

#: The final fit: coef, raw and mesh intercepts, feature columns, n_components.
MODEL_NPZ = "model.npz"
#: The CV's per-vertex and per-target R², the R² path over n_components, the cumulative error curve.
CV_NPZ = "cv.npz"
#: Each frame's held-out mean per-vertex error, (n_frames,) float32 in ``frames.parquet``'s row order.
FRAME_ERROR_FILE = "frame_vertex_error.npy"
#: Points of the cumulative vertex error curve ``cv.npz`` keeps for the card's figure (the empirical CDF at the
#: 0, 0.1, ..., 100 % quantiles: finer than the figure's pixels, and a fixed size whatever the frames).
CARD_ERROR_CURVE_POINTS = 1001
#: The MLflow run that made these files (its id, name, store) and the data digest.
TRACKING_JSON = "tracking.json"
#: The CV's summary metrics (also ``paths.metrics_file`` for DVC).
METRICS_JSON = "metrics.json"
#: In ``paths.families_model_dir``/<family> instead of a fit: the family was not fitted (``families.<f>.features=none``,
#: or the tables do not carry it) and why (``{"family", "reason"}``); ``release_family@<family>`` then records that
SKIPPED_JSON = "skipped.json"
