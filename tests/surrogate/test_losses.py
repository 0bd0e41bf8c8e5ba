"""Loss components against hand-computed values."""

import math

import numpy as np
import torch

from calendaring.data.dataset import kl_divergence
from surrogate.losses import SurrogateLoss, kl_per_row


def _example():
    # two rows of 2 x 2 histograms and 3-point curves
    d_true = torch.tensor([[[0.5, 0.5], [0.0, 0.0]], [[0.1, 0.2], [0.3, 0.4]]])
    d_pred = torch.tensor([[[0.25, 0.25], [0.25, 0.25]], [[0.1, 0.2], [0.3, 0.4]]])
    p_true = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    p_pred = p_true + torch.tensor([[0.1, -0.1, 0.1], [0.2, 0.0, 0.0]])
    return p_pred, p_true, d_pred, d_true


def test_components_match_hand_values():
    p_pred, p_true, d_pred, d_true = _example()
    t = SurrogateLoss()(p_pred, p_true, d_pred, d_true)
    mse = (3 * 0.01 + 0.04) / 6  # mean over the six points
    kl = (0.5 * math.log(2) * 2 + 0.0) / 2  # KL([.5,.5,0,0] || uniform) = ln 2; row 2 is 0
    np.testing.assert_allclose(float(t.mse), mse, rtol=1e-5)
    np.testing.assert_allclose(float(t.kl), kl, rtol=1e-5)  # the 1e-8 floor changes ~1e-7
    np.testing.assert_allclose(float(t.total), 0.7 * mse + 0.3 * kl, rtol=1e-5)


def test_weights_and_row_mask():
    p_pred, p_true, d_pred, d_true = _example()
    t = SurrogateLoss(1.0, 0.0)(p_pred, p_true, d_pred, d_true, torch.tensor([1.0, 0.0]))
    np.testing.assert_allclose(float(t.kl), math.log(2), rtol=1e-5)  # only row 1 counts
    np.testing.assert_allclose(float(t.total), float(t.mse), rtol=1e-7)


def test_floor_matches_dataset_kl():
    g = torch.Generator().manual_seed(0)
    a = torch.softmax(torch.randn(3, 900, generator=g) * 3, -1).reshape(3, 30, 30)
    b = torch.softmax(torch.randn(3, 900, generator=g) * 3, -1).reshape(3, 30, 30)
    a[0, :5] = 0.0  # exact zeros are floored at 1e-8
    a = a / a.sum(dim=(1, 2), keepdim=True)
    ours = kl_per_row(a.double(), b.double()).numpy()
    np.testing.assert_allclose(ours, kl_divergence(a.numpy(), b.numpy()), rtol=1e-6)
    assert np.all(ours >= 0)
