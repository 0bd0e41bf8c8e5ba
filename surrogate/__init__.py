"""surrogate: the paper's dual-branch MLP for the pressure curve and breakage distribution.

    >>> import surrogate
    >>> m = surrogate.load("model.pt")             # a single model or a deep ensemble
    >>> pred = m.predict({"d0": 9e-6})             # physical units; others: reference values
    >>> pred.pressure, pred.distribution           # (1, 196) [Pa], (1, 30, 30) probabilities

Modules: :mod:`~surrogate.model` (architecture), :mod:`~surrogate.data` (splits,
normalisation, torch dataset), :mod:`~surrogate.losses`, :mod:`~surrogate.train`,
:mod:`~surrogate.ensemble`, :mod:`~surrogate.baseline` (PCA + GP),
:mod:`~surrogate.evaluate` (metrics, noise floors, CV, Table 3, Fig. 5),
:mod:`~surrogate.learning` (error on held-out seed means against training runs),
:mod:`~surrogate.checkpoint` and :mod:`~surrogate.api` (files and the Python interface),
:mod:`~surrogate.cli`.
"""

from surrogate.api import Prediction, SurrogateModel, load
from surrogate.checkpoint import CheckpointError
from surrogate.data import Normalisation, SurrogateDataset, split_indices
from surrogate.ensemble import ensemble_forward, train_ensemble
from surrogate.losses import LossTerms, SurrogateLoss
from surrogate.model import DualBranchMLP, ModelConfig, ResidualBlock
from surrogate.train import Collector, TrainConfig, Trainer, TrainResult, train

__all__ = ["CheckpointError", "Collector", "DualBranchMLP", "LossTerms", "ModelConfig",
           "Normalisation", "Prediction", "ResidualBlock", "SurrogateDataset", "SurrogateLoss",
           "SurrogateModel", "TrainConfig", "TrainResult", "Trainer", "ensemble_forward",
           "load", "split_indices", "train", "train_ensemble"]
