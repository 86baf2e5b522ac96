"""The averaged pose head: symmetric estimates are aligned before they are averaged; bundles
with another encoder are refused."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tracker.geometry import mean_pose, rotation_error_deg
from tracker.regressors import HeadEnsemble


class FixedHead:
    """A stand-in pose head that answers the same pose for every crop."""
    rotation_frame = "ray"

    def __init__(self, R, t, obj_ids=(10,)):
        self.R, self.t, self.obj_ids = np.asarray(R, float), np.asarray(t, float), list(obj_ids)

    def predict(self, mu, obj_ids, boxes, K, mode="regression"):
        n = len(obj_ids)
        return np.repeat(self.R[None], n, 0), np.repeat(self.t[None], n, 0)


def test_symmetric_estimates_are_aligned_before_averaging():
    R0 = Rotation.from_euler("xyz", [20, 40, -30], degrees=True).as_matrix()
    flip = Rotation.from_euler("z", 180, degrees=True).as_matrix()  # the object's symmetry (model frame)
    near = Rotation.from_rotvec([0.0, 0.1, 0.0]).as_matrix()
    t = np.array([0.0, 0.0, 900.0])
    heads = [FixedHead(R0, t), FixedHead(R0 @ near @ flip, t)]  # the second: R0 turned a little, then flipped
    ens = HeadEnsemble(heads, {10: np.stack([np.eye(3), flip])})
    R, tt = ens.predict(np.zeros((1, 4)), [10], np.array([[0, 0, 10, 10]]), np.eye(3))
    expected, _ = mean_pose(np.stack([R0, R0 @ near])[:, None], np.stack([t, t])[:, None])
    assert rotation_error_deg(R[0], expected[0]) < 1e-4
    assert rotation_error_deg(R[0], R0) == pytest.approx(np.degrees(0.05), abs=1e-3)  # half of the small turn
    assert np.allclose(tt, t)
    plain = HeadEnsemble(heads, {})  # without the symmetry the flipped estimate drags the mean far off
    assert rotation_error_deg(plain.predict(np.zeros((1, 4)), [10], np.zeros((1, 4)), np.eye(3))[0][0], R0) > 45


def test_ensembles_flatten_and_refuse_heads_of_other_objects():
    a, b = FixedHead(np.eye(3), [0, 0, 500]), FixedHead(np.eye(3), [0, 0, 2000])
    ens = HeadEnsemble([HeadEnsemble([a, b], {}), a], {})
    assert len(ens.members) == 3
    from tracker.errors import UserError
    with pytest.raises(UserError, match="cannot be averaged"):
        HeadEnsemble([a, FixedHead(np.eye(3), [0, 0, 1], obj_ids=(1,))], {})
