"""Design matrix: [20 AU | 3 pose | 60 pose x AU] (card, "Method"; v2 trains with pose x AU interactions)."""

from __future__ import annotations

import numpy as np

from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS, feature_columns


def design_matrix(au: np.ndarray, pose: np.ndarray, use_pose: bool, interactions: bool) -> np.ndarray:
    """Rows of the regression's input.

    Parameters
    ----------
    au : ndarray, shape (n, 20)
        AU intensities in ``schema.AU_COLUMNS`` order.
    pose : ndarray, shape (n, 3)
        Pitch, Yaw, Roll in radians (the model's order).
    use_pose, interactions : bool
        Append the 3 pose covariates; append the 60 pose x AU products (pose-major,
        ``schema.interaction_columns``).

    Returns
    -------
    X : ndarray, shape (n, 20 | 23 | 83), float64
    """
    au = np.asarray(au, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    if au.ndim != 2 or au.shape[1] != len(AU_COLUMNS) or pose.shape != (au.shape[0], len(POSE_COLUMNS)):
        raise ValueError(f"design_matrix: need au (n, 20) and pose (n, 3), got {au.shape} and {pose.shape}")
    n_cols = len(feature_columns(use_pose, interactions))
    X = np.empty((au.shape[0], n_cols))
    X[:, :20] = au
    if use_pose:
        X[:, 20:23] = pose
    if interactions:
        X[:, 23:] = (pose[:, :, None] * au[:, None, :]).reshape(au.shape[0], -1)
    return X
