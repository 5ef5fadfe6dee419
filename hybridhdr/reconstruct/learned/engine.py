"""Checkpoint loading, the per-window recurrent reconstructor and the driver engine (needs PyTorch)."""

from __future__ import annotations

import math
import os

import numpy as np

from .. import _engine as E
from .params import WEIGHTS_HELP, LearnedParams, WeightsRequiredError
from .voxel import events_to_voxel_grid, normalize_voxel_grid, voxel_grid_torch

__all__ = ["load_checkpoint", "load_network", "Reconstructor", "LearnedEngine", "torch_device", "export_onnx"]

METHOD_ARCH = {"e2vid": "E2VIDRecurrent", "firenet": "FireNet"}


def _torch():
    try:
        import torch
    except ImportError as e:
        raise ImportError("the learned methods (e2vid, firenet) need PyTorch: "
                          "pip install 'hybridhdr[learned]' (torch>=2.1)") from e
    return torch


def torch_device(device: str = "auto"):
    torch = _torch()
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but PyTorch sees no CUDA device")
    return torch.device(device)


def load_checkpoint(path, allow_pickle: bool = False) -> tuple[str | None, dict, dict]:
    """(arch, model config, state_dict) of a released checkpoint (``{"arch", "model" or
    "config": {"model"}, "state_dict"}``) or of a bare state dict (arch None, config {})."""
    torch = _torch()
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"weights file {path} not found")
    try:
        raw = torch.load(path, map_location="cpu", weights_only=not allow_pickle)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a file it cannot read
        if not allow_pickle and "weights_only" in str(e):
            raise ValueError(f"{path}: the checkpoint holds objects the safe loader refuses; if you trust the "
                             f"file, set allow_pickle=true (--set allow_pickle=true)") from None
        raise ValueError(f"{path}: not a PyTorch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a checkpoint dict, got {type(raw).__name__}")
    if "state_dict" in raw:
        sd = raw["state_dict"]
        arch = raw.get("arch")
        cfg = raw.get("model")
        if cfg is None and isinstance(raw.get("config"), dict):
            cfg = raw["config"].get("model")
        cfg = dict(cfg) if isinstance(cfg, dict) else {}
    elif raw and all(torch.is_tensor(v) for v in raw.values()):
        sd, arch, cfg = raw, None, {}
    else:
        raise ValueError(f"{path}: no 'state_dict' in the checkpoint (keys {sorted(map(str, raw))[:10]})")
    if not isinstance(sd, dict):
        raise ValueError(f"{path}: 'state_dict' is not a dict")
    return (str(arch) if arch is not None else None), cfg, sd


def load_network(method: str, params: LearnedParams):
    """The network of ``method`` with the checkpoint ``params.weights`` loaded (strict: every
    key and shape must match; no renaming), in eval mode on the resolved device."""
    from .networks import build_network
    if params.weights is None:
        raise WeightsRequiredError(f"method {method!r} needs trained weights, which hybridhdr never downloads: "
                                   f"{WEIGHTS_HELP[method]}")
    arch, cfg, sd = load_checkpoint(params.weights, params.allow_pickle)
    want = METHOD_ARCH[method]
    if arch is not None and arch != want:
        raise ValueError(f"{params.weights}: checkpoint architecture {arch!r}, but method {method!r} "
                         f"expects {want!r}")
    if "num_bins" in cfg and int(cfg["num_bins"]) != params.num_bins:
        raise ValueError(f"{params.weights}: the checkpoint was trained with num_bins={cfg['num_bins']}, "
                         f"but num_bins={params.num_bins}")
    cfg = dict(cfg, num_bins=params.num_bins)
    net = build_network(want, cfg)
    res = net.load_state_dict(sd, strict=False)
    if res.missing_keys or res.unexpected_keys:
        raise ValueError(f"{params.weights}: state_dict does not match {want} {cfg}: missing keys "
                         f"{res.missing_keys[:8]}, unexpected keys {res.unexpected_keys[:8]}")
    device = torch_device(params.device)
    return net.to(device).eval(), device


class Reconstructor:
    """One network with its recurrent state: ``step(voxel_grid) -> image`` (H, W) float32 in
    [0, 1]. The input is padded (reflection, centred) to a multiple of the network's
    down-sampling and the output cropped back."""

    def __init__(self, net, device, shape, clip: bool):
        self.net = net
        self.device = device
        self.shape = (int(shape[0]), int(shape[1]))
        self.clip = clip
        m = int(getattr(net, "size_multiple", 1))
        H, W = self.shape
        Hp, Wp = m * math.ceil(H / m), m * math.ceil(W / m)
        self.pad = (math.ceil((Wp - W) / 2), (Wp - W) // 2, math.ceil((Hp - H) / 2), (Hp - H) // 2)
        self.states = None

    def reset(self) -> None:
        self.states = None

    def step(self, grid) -> np.ndarray:
        """One recurrent step on a voxel grid (numpy array, or a tensor already on the device)."""
        torch = _torch()
        with torch.inference_mode():
            if isinstance(grid, torch.Tensor):
                x = grid.to(self.device, torch.float32)[None]
            else:
                x = torch.from_numpy(np.ascontiguousarray(grid, np.float32))[None].to(self.device)
            l, r, t, b = self.pad
            if any(self.pad):
                mode = "reflect" if max(l, r) < x.shape[3] and max(t, b) < x.shape[2] else "replicate"
                x = torch.nn.functional.pad(x, self.pad, mode=mode)
            img, self.states = self.net(x, self.states)
            H, W = self.shape
            img = img[0, 0, t:t + H, l:l + W]
            if self.clip:
                img = img.clamp(0.0, 1.0)
            return img.float().cpu().numpy()


class LearnedEngine(E.Engine):
    """Driver engine of ``e2vid`` / ``firenet``: buffers the events of each window
    [previous output time, t) and, at :meth:`output` (t), builds the window's voxel grid and runs
    the network once, advancing its recurrent state (so, unlike the filters' outputs, each output
    time is computed once, in order; a repeated call at the same t returns the same image)."""

    def __init__(self, shape, params: LearnedParams, method: str):
        super().__init__(shape, 1)
        self.params = params
        self.method = method
        net, device = load_network(method, params)
        self.rec = Reconstructor(net, device, self.shape, clip=(method == "firenet"))
        self._buf: list = []
        self._last = None
        self.n_windows = 0
        # on a GPU the events go to the device as they arrive and the voxel grids are built there
        # (voxel_grid_torch): per window only the output image comes back
        self.on_device = getattr(device, "type", "cpu") == "cuda"

    def set_thresholds(self, c_on, c_off) -> None:
        raise ValueError(f"method {self.method!r} does not take a per-pixel threshold map")

    def start(self, t_start_us=None) -> int:
        self.rec.reset()
        self._buf = []
        self._last = None
        return int(t_start_us) if t_start_us is not None else 0

    def process(self, t, x, y, p, i0, i1) -> None:
        if i1 <= i0:
            return
        if self.on_device:
            torch = _torch()
            dev = self.rec.device
            # t int64, p int8; x, y as int32 (PyTorch's uint16 has few kernels): uint16 columns go
            # as they are, viewed as int16 (half the bytes of int32, no host conversion), and are
            # widened on the device (& 0xFFFF undoes the sign: the same values)
            cols = [torch.from_numpy(np.ascontiguousarray(t[i0:i1], dtype=np.int64)).to(dev)]
            for a in (x, y):
                a = a[i0:i1]
                if a.dtype == np.uint16:
                    d = torch.from_numpy(np.ascontiguousarray(a).view(np.int16)).to(dev).to(torch.int32) & 0xFFFF
                else:
                    d = torch.from_numpy(np.ascontiguousarray(a, dtype=np.int32)).to(dev)
                cols.append(d)
            cols.append(torch.from_numpy(np.ascontiguousarray(p[i0:i1], dtype=np.int8)).to(dev))
            self._buf.append(tuple(cols))
        else:
            self._buf.append((t[i0:i1].copy(), x[i0:i1].copy(), y[i0:i1].copy(), p[i0:i1].copy()))
        self.n_events += i1 - i0

    def window_grid(self):
        """The (normalised) voxel grid of the buffered events (a tensor on the GPU when
        :attr:`on_device`, else a numpy array)."""
        if self.on_device:
            torch = _torch()
            if self._buf:
                t, x, y, p = (torch.cat(c) for c in zip(*self._buf))
            else:
                t = x = y = p = torch.zeros(0, dtype=torch.int64, device=self.rec.device)
            return voxel_grid_torch(t, x, y, p, self.params.num_bins, self.shape, self.params.normalize)
        if self._buf:
            t, x, y, p = (np.concatenate(c) for c in zip(*self._buf))
        else:
            t = x = y = p = np.zeros(0, np.int64)
        g = events_to_voxel_grid(t, x, y, p, self.params.num_bins, self.shape)
        return normalize_voxel_grid(g) if self.params.normalize else g

    def output(self, t_us: int) -> np.ndarray:
        if self._last is not None and self._last[0] == t_us:
            return self._last[1].copy()
        img = self.rec.step(self.window_grid())
        self._buf = []
        self.n_windows += 1
        self._last = (t_us, img)
        return img.copy()


def export_onnx(net, path, shape, states=None) -> list[str]:
    """Write one recurrent step of ``net`` as ONNX (optional extra ``onnx``: onnx, onnxscript;
    run it with onnxruntime). Inputs ``x`` (1, B, H, W) and ``state0``, ``state1``, … (the flat
    recurrent state, zeros for the first window); outputs ``image`` then the new states in the
    same order. ``shape`` is the (padded) network input size (H, W). Returns the input names."""
    torch = _torch()
    import warnings

    class _Step(torch.nn.Module):
        def __init__(self, inner):
            super().__init__()
            self.inner = inner

        def forward(self, x, *st):
            img, new = self.inner(x, list(st))
            return (img, *new)

    H, W = int(shape[0]), int(shape[1])
    x = torch.zeros(1, int(getattr(net, "num_bins", 5)), H, W)
    if states is None:
        with torch.no_grad():
            _, states = net(x, None)
    names = ["x"] + [f"state{i}" for i in range(len(states))]
    with warnings.catch_warnings():  # the exporter's own deprecation chatter
        warnings.simplefilter("ignore")
        torch.onnx.export(_Step(net).eval(), (x, *states), os.fspath(path), input_names=names,
                          output_names=["image"] + [f"new_state{i}" for i in range(len(states))],
                          verbose=False)
    return names
