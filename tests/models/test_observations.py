"""models/observations.py: observations checked against the shape a model predicts."""
import numpy as np
import pytest
import torch

from bayespd.models.observations import check_shape


def test_data_of_the_right_shape_come_back_as_float64_tensors():
    y = check_shape(np.arange(6, dtype=np.float32).reshape(3, 2) / 3, (3, 2), "y", "")
    assert isinstance(y, torch.Tensor) and y.dtype == torch.float64 and y.shape == (3, 2)
    np.testing.assert_array_equal(y.numpy(), np.arange(6, dtype=np.float32).reshape(3, 2) / 3)
    assert check_shape([[1.0, 2.0]], [1, 2], "y", "").shape == (1, 2)  # list shapes compare as tuples


def test_wrong_shapes_and_non_finite_data_name_the_fix():
    with pytest.raises(ValueError, match=r"the DIC data has shape \(2, 2\) but the model predicts \(3, 2\): "
                                         r"observe the scene's points"):
        check_shape(np.zeros((2, 2)), (3, 2), "the DIC data", "observe the scene's points")
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="y contains NaN or inf: drop those entries or mask them"):
            check_shape([[0.0, bad]], (1, 2), "y", "")
