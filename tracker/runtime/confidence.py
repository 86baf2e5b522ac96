"""A pose's confidence: three checks the pipeline has for free, multiplied (each in [0, 1]).

- the detector's score for the box (1 for a ground-truth box);
- the encoder's own check (the AAE's): the cosine similarity between the crop's latent code
  and the nearest code of a rendered view of that object in the bundle's codebook; a crop that
  looks like no view of the object scores low;
- the pose's agreement with its box: the IoU between the box and the box of the object's
  points projected at the estimated pose.

Measured on the LM-O dev frames with the bundle's detector (docs/experiments/stop-38.md): as a
ranking of poses whose own AR_MSSD is >= 0.5 above the rest, ROC AUC 0.774 for the detector's
score alone, 0.806 for the code similarity, 0.791 for the box agreement, 0.827 for the product.
``eval`` reports it for every run (metrics JSON: ``confidence.auc``).
"""
from __future__ import annotations

import numpy as np

from tracker.core.geometry import box_from_points, iou_matrix, project

UNCERTAIN_BELOW = 0.3  # on dev, poses above: 53 % good, below: 11 % (good: AR_MSSD >= 0.5)


def box_iou(a, b) -> float:
    """IoU of two (x, y, w, h) boxes."""
    return float(iou_matrix(a, b)[0, 0])


def box_agreement(points: np.ndarray, K, R, t, box) -> float:
    """IoU between ``box`` and the box of ``points`` (model frame, mm) projected at (R, t);
    0 where the pose puts the object behind the camera."""
    if (np.asarray(R) @ np.asarray(points).T + np.asarray(t).reshape(3, 1))[2].min() <= 1.0:
        return 0.0
    return box_iou(box_from_points(project(points, K, R, t)), box)


def code_similarity(mu: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Cosine similarity of each latent code (N, D) to its nearest (L2-normalised) ``codes``."""
    q = mu / (np.linalg.norm(mu, axis=1, keepdims=True) + 1e-9)
    return (q @ codes.T).max(axis=1)


def confidence(detector_score: float, similarity: float, agreement: float) -> float:
    """The product of the three checks, each clipped to [0, 1]."""
    return float(np.clip(detector_score, 0, 1) * np.clip(similarity, 0, 1) * np.clip(agreement, 0, 1))
