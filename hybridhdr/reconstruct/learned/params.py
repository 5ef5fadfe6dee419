"""Parameters of the learned events-only methods (pure Python: importing them needs no PyTorch)."""

from __future__ import annotations

import os
from dataclasses import dataclass

from ..params import _ParamsMixin

__all__ = ["LearnedParams", "E2VIDParams", "FireNetParams", "WEIGHTS_HELP", "WeightsRequiredError"]

#: Where the authors publish their checkpoints (hybridhdr never downloads them).
WEIGHTS_HELP = {
    "e2vid": ("E2VID_lightweight.pth.tar, linked from the README of https://github.com/uzh-rpg/rpg_e2vid "
              "(Rebecq et al., TPAMI 2019); download it yourself and pass --weights FILE "
              "(Python: params={'weights': FILE})"),
    "firenet": ("firenet_1000.pth.tar, linked from the README of the cedric/firenet branch of "
                "https://github.com/cedric-scheerlinck/rpg_e2vid (Scheerlinck et al., WACV 2020); download it "
                "yourself and pass --weights FILE (Python: params={'weights': FILE})"),
}


class WeightsRequiredError(ValueError):
    """A learned method was asked to run without a checkpoint (``weights``); the message says
    where the authors publish theirs. A ``ValueError``: the CLI exits with status 2."""


@dataclass(frozen=True, kw_only=True)
class LearnedParams(_ParamsMixin):
    """Common parameters of the learned events-only reconstructions (E2VID, FireNet).

    Parameters
    ----------
    weights : str or None
        The checkpoint file (``.pth`` / ``.pth.tar``) as the authors release it: a dict with
        ``arch``, the model configuration (``model`` or ``config.model``) and ``state_dict``,
        or a bare state dict. Required to run; never downloaded.
    num_bins : int
        Temporal bins B of the event voxel grid (5 in both papers; must equal the checkpoint's).
    device : str
        "auto" (a CUDA device when PyTorch sees one, else the CPU), "cpu", "cuda" or "cuda:N".
    normalize : bool
        Normalise each window's voxel grid so that its non-zero entries have mean 0 and
        standard deviation 1 (as in training; both papers).
    allow_pickle : bool
        Load the checkpoint with full unpickling (``torch.load(weights_only=False)``). Off by
        default: the released files hold only tensors, strings, numbers and dicts, which the
        safe loader reads; turn on only for a file you trust that needs it.
    """

    _toml_table = ""
    _arch = ""

    weights: str | None = None
    num_bins: int = 5
    device: str = "auto"
    normalize: bool = True
    allow_pickle: bool = False

    def __post_init__(self):
        w = self.weights
        if isinstance(w, os.PathLike):
            object.__setattr__(self, "weights", os.fspath(w))
        elif w is not None and not isinstance(w, str):
            raise TypeError(f"{type(self).__name__}.weights must be a path or None, got {type(w).__name__}")
        if isinstance(self.num_bins, bool) or not isinstance(self.num_bins, int) or self.num_bins < 1:
            raise ValueError(f"{type(self).__name__}.num_bins must be an int >= 1, got {self.num_bins!r}")
        if not isinstance(self.device, str) or not (self.device in ("auto", "cpu", "cuda")
                                                    or (self.device.startswith("cuda:")
                                                        and self.device[5:].isdigit())):
            raise ValueError(f"{type(self).__name__}.device must be 'auto', 'cpu', 'cuda' or 'cuda:N', "
                             f"got {self.device!r}")
        self._bool("normalize")
        self._bool("allow_pickle")


@dataclass(frozen=True, kw_only=True)
class E2VIDParams(LearnedParams):
    """E2VID (Rebecq, Ranftl, Koltun, Scaramuzza, TPAMI 2019): recurrent UNet (ConvLSTM after
    each encoder) on event voxel grids; output sigmoid(·) in [0, 1]. See :class:`LearnedParams`."""

    _toml_table = "e2vid"
    _arch = "E2VIDRecurrent"


@dataclass(frozen=True, kw_only=True)
class FireNetParams(LearnedParams):
    """FireNet (Scheerlinck, Rebecq, Gehrig, Barnes, Mahony, Scaramuzza, WACV 2020): light
    recurrent network (ConvGRUs, no downsampling); output clipped to [0, 1]. See
    :class:`LearnedParams`."""

    _toml_table = "firenet"
    _arch = "FireNet"
