"""The estimator and the release format: sufficient statistics, exact PLS, scores, the NPZ, prediction and its checks."""
