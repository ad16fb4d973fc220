"""The files of the evaluate stage's output folder (``paths.model_dir``, ``build/model/``)."""

MODEL_NPZ = "model.npz"
CV_NPZ = "cv.npz"
#: Points of the cumulative vertex error curve ``cv.npz`` keeps for the card's figure (the empirical CDF at the
#: 0, 0.1, ..., 100 % quantiles: finer than the figure's pixels, and a fixed size whatever the frames).
CARD_ERROR_CURVE_POINTS = 1001
TRACKING_JSON = "tracking.json"
METRICS_JSON = "metrics.json"
