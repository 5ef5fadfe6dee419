"""E2VID's recurrent UNet and FireNet, written from their papers (needs PyTorch).

* E2VID (Rebecq, Ranftl, Koltun, Scaramuzza, "High Speed and High Dynamic Range Video with an
  Event Camera", TPAMI 2019, §3.2 and Fig. 3): a head convolution, E encoders (5×5 stride-2
  convolution, then a ConvLSTM), R residual blocks, E decoders (5×5 up-sampling layers) with
  skip connections by summation, and a 1×1 prediction layer followed by a sigmoid.
* FireNet (Scheerlinck, Rebecq, Gehrig, Barnes, Mahony, Scaramuzza, "Fast Image Reconstruction
  with an Event Camera", WACV 2020, §3 and Fig. 2): H (3×3 conv) → G1 (ConvGRU) → R1
  (residual block) → G2 (ConvGRU) → R2 (residual block) → P (1×1 conv), 16 channels, no
  down-sampling, no output activation.

Module and parameter names follow the authors' released checkpoints so that their
``state_dict`` loads with ``load_state_dict(strict=True)`` and no key renaming: E2VID's keys
start with ``unetrecurrent.``, FireNet's with ``net.`` (see ``tests/reconstruct/test_learned.py``
for the full published key/shape tables these modules are checked against).

Recurrent states are flat lists of tensors (E2VID: h₀, c₀, h₁, c₁, …; FireNet: one hidden state
per ConvGRU), ``None`` meaning zeros; ``forward(x, states) -> (image, states)``.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["E2VIDRecurrent", "FireNet", "build_network", "E2VID_RELEASED_CONFIG", "FIRENET_RELEASED_CONFIG"]

#: The configuration stored in E2VID_lightweight.pth.tar (``model`` entry of the checkpoint).
E2VID_RELEASED_CONFIG = {"num_bins": 5, "skip_type": "sum", "recurrent_block_type": "convlstm", "num_encoders": 3,
                         "base_num_channels": 32, "num_residual_blocks": 2, "use_upsample_conv": False,
                         "norm": "BN"}
#: The configuration of firenet_1000.pth.tar.
FIRENET_RELEASED_CONFIG = {"num_bins": 5, "skip_type": "no_skip", "recurrent_block_type": "convgru",
                           "base_num_channels": 16, "num_residual_blocks": 2, "norm": None, "kernel_size": 3,
                           "recurrent_blocks": {"resblock": [0]}}


def _norm_layer(norm, channels):
    if norm == "BN":
        return nn.BatchNorm2d(channels)
    if norm == "IN":
        return nn.InstanceNorm2d(channels, track_running_stats=True)
    return None


def _check_norm(norm):
    if norm not in (None, "none", "None", "BN", "IN"):
        raise ValueError(f"norm must be None, 'BN' or 'IN', got {norm!r}")
    return None if norm in ("none", "None") else norm


class ConvLayer(nn.Module):
    """Convolution (``conv2d``), optional normalisation (``norm_layer``), optional ReLU."""

    def __init__(self, cin, cout, k, stride=1, padding=0, relu=True, norm=None):
        super().__init__()
        self.conv2d = nn.Conv2d(cin, cout, k, stride, padding, bias=norm != "BN")
        nl = _norm_layer(norm, cout)
        if nl is not None:
            self.norm_layer = nl
        self.relu = relu

    def forward(self, x):
        x = self.conv2d(x)
        if hasattr(self, "norm_layer"):
            x = self.norm_layer(x)
        return torch.relu(x) if self.relu else x


class TransposedConvLayer(nn.Module):
    """×2 up-sampling by a stride-2 transposed convolution (``transposed_conv2d``) + norm + ReLU."""

    def __init__(self, cin, cout, k, padding=0, norm=None):
        super().__init__()
        self.transposed_conv2d = nn.ConvTranspose2d(cin, cout, k, stride=2, padding=padding, output_padding=1,
                                                    bias=norm != "BN")
        nl = _norm_layer(norm, cout)
        if nl is not None:
            self.norm_layer = nl

    def forward(self, x):
        x = self.transposed_conv2d(x)
        if hasattr(self, "norm_layer"):
            x = self.norm_layer(x)
        return torch.relu(x)


class UpsampleConvLayer(nn.Module):
    """×2 bilinear up-sampling then a convolution (``conv2d``) + norm + ReLU."""

    def __init__(self, cin, cout, k, padding=0, norm=None):
        super().__init__()
        self.conv2d = nn.Conv2d(cin, cout, k, 1, padding, bias=norm != "BN")
        nl = _norm_layer(norm, cout)
        if nl is not None:
            self.norm_layer = nl

    def forward(self, x):
        x = self.conv2d(F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False))
        if hasattr(self, "norm_layer"):
            x = self.norm_layer(x)
        return torch.relu(x)


class ResidualBlock(nn.Module):
    """x + conv2(relu(conv1(x))) (3×3, with ``bn1``/``bn2`` for BN or IN), then ReLU."""

    def __init__(self, channels, norm=None):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, 1, 1, bias=norm != "BN")
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1, bias=norm != "BN")
        if norm == "BN":
            self.bn1, self.bn2 = nn.BatchNorm2d(channels), nn.BatchNorm2d(channels)
        elif norm == "IN":
            self.bn1, self.bn2 = nn.InstanceNorm2d(channels), nn.InstanceNorm2d(channels)

    def forward(self, x):
        y = self.conv1(x)
        if hasattr(self, "bn1"):
            y = self.bn1(y)
        y = self.conv2(torch.relu(y))
        if hasattr(self, "bn2"):
            y = self.bn2(y)
        return torch.relu(y + x)


class ConvLSTM(nn.Module):
    """Convolutional LSTM: one convolution ``Gates`` of [x, h] gives the input, forget, output
    and candidate gates (in that channel order); c' = f c + i g, h' = o tanh(c')."""

    n_states = 2

    def __init__(self, cin, hidden, k=3):
        super().__init__()
        self.hidden = hidden
        self.Gates = nn.Conv2d(cin + hidden, 4 * hidden, k, padding=k // 2)

    def forward(self, x, h, c):
        if h is None:
            h = x.new_zeros((x.shape[0], self.hidden) + tuple(x.shape[2:]))
        if c is None:
            c = torch.zeros_like(h)
        i, f, o, g = self.Gates(torch.cat([x, h], 1)).chunk(4, 1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, [h, c]


class ConvGRU(nn.Module):
    """Convolutional GRU with gates ``reset_gate``, ``update_gate`` and candidate ``out_gate``:
    h' = (1 − z) h + z tanh(W_o [x, r h])."""

    n_states = 1

    def __init__(self, cin, hidden, k=3):
        super().__init__()
        self.hidden = hidden
        self.reset_gate = nn.Conv2d(cin + hidden, hidden, k, padding=k // 2)
        self.update_gate = nn.Conv2d(cin + hidden, hidden, k, padding=k // 2)
        self.out_gate = nn.Conv2d(cin + hidden, hidden, k, padding=k // 2)

    def forward(self, x, h, _unused=None):
        if h is None:
            h = x.new_zeros((x.shape[0], self.hidden) + tuple(x.shape[2:]))
        xh = torch.cat([x, h], 1)
        z = torch.sigmoid(self.update_gate(xh))
        r = torch.sigmoid(self.reset_gate(xh))
        cand = torch.tanh(self.out_gate(torch.cat([x, r * h], 1)))
        h = h * (1 - z) + cand * z
        return h, [h]


def _cell(kind, cin, hidden, k=3):
    if kind == "convlstm":
        return ConvLSTM(cin, hidden, k)
    if kind == "convgru":
        return ConvGRU(cin, hidden, k)
    raise ValueError(f"recurrent_block_type must be 'convlstm' or 'convgru', got {kind!r}")


class RecurrentConvLayer(nn.Module):
    """``conv`` (a :class:`ConvLayer`) followed by a recurrent cell ``recurrent_block``."""

    def __init__(self, cin, cout, k, stride, padding, kind, norm=None):
        super().__init__()
        self.conv = ConvLayer(cin, cout, k, stride, padding, relu=True, norm=norm)
        self.recurrent_block = _cell(kind, cout, cout, 3)

    def forward(self, x, states):
        return self.recurrent_block(self.conv(x), *states)


class RecurrentResidualLayer(nn.Module):
    """``conv`` (a :class:`ResidualBlock`) followed by a recurrent cell ``recurrent_block``."""

    def __init__(self, channels, kind, norm=None):
        super().__init__()
        self.conv = ResidualBlock(channels, norm)
        self.recurrent_block = _cell(kind, channels, channels, 3)

    def forward(self, x, states):
        return self.recurrent_block(self.conv(x), *states)


def _split_states(states, blocks):
    """Per-block state lists from a flat list (None: zeros)."""
    out, i = [], 0
    for b in blocks:
        n = b.recurrent_block.n_states
        out.append(list(states[i:i + n]) if states is not None else [None] * n)
        i += n
    if states is not None and i != len(states):
        raise ValueError(f"expected {i} state tensors, got {len(states)}")
    return out


class UNetRecurrent(nn.Module):
    def __init__(self, num_bins, skip_type="sum", kind="convlstm", num_encoders=3, base=32, num_res=2,
                 norm=None, use_upsample_conv=True):
        super().__init__()
        if skip_type not in ("sum", "concat"):
            raise ValueError(f"skip_type must be 'sum' or 'concat', got {skip_type!r}")
        self.skip_type = skip_type
        self.num_encoders = int(num_encoders)
        self.head = ConvLayer(num_bins, base, 5, 1, 2, relu=True)  # no normalisation on the head
        self.encoders = nn.ModuleList(
            RecurrentConvLayer(base * 2 ** i, base * 2 ** (i + 1), 5, 2, 2, kind, norm)
            for i in range(self.num_encoders))
        top = base * 2 ** self.num_encoders
        self.resblocks = nn.ModuleList(ResidualBlock(top, norm) for _ in range(int(num_res)))
        Up = UpsampleConvLayer if use_upsample_conv else TransposedConvLayer
        mult = 1 if skip_type == "sum" else 2
        self.decoders = nn.ModuleList(
            Up(mult * base * 2 ** (i + 1), base * 2 ** i, 5, padding=2, norm=norm)
            for i in reversed(range(self.num_encoders)))
        self.pred = ConvLayer(mult * base, 1, 1, relu=False, norm=norm)

    def _skip(self, a, b):
        return a + b if self.skip_type == "sum" else torch.cat([a, b], 1)

    def forward(self, x, states=None):
        x = self.head(x)
        head = x
        skips, new_states = [], []
        for enc, st in zip(self.encoders, _split_states(states, self.encoders)):
            x, s = enc(x, st)
            skips.append(x)
            new_states.extend(s)
        for rb in self.resblocks:
            x = rb(x)
        for dec, skip in zip(self.decoders, reversed(skips)):
            x = dec(self._skip(x, skip))
        return torch.sigmoid(self.pred(self._skip(x, head))), new_states


class E2VIDRecurrent(nn.Module):
    """E2VID (recurrent): ``forward(voxel (N, B, H, W), states) -> (image in [0, 1], states)``;
    H and W must be multiples of 2^num_encoders (:class:`~.engine.Reconstructor` pads)."""

    def __init__(self, config: dict | None = None):
        super().__init__()
        c = dict(E2VID_RELEASED_CONFIG, **(config or {}))
        self.config = c
        self.num_bins = int(c["num_bins"])
        self.num_encoders = int(c["num_encoders"])
        self.unetrecurrent = UNetRecurrent(
            self.num_bins, c["skip_type"], c["recurrent_block_type"], self.num_encoders,
            int(c["base_num_channels"]), int(c["num_residual_blocks"]), _check_norm(c.get("norm")),
            bool(c["use_upsample_conv"]))

    @property
    def size_multiple(self) -> int:
        return 2 ** self.num_encoders

    def forward(self, x, states=None):
        return self.unetrecurrent(x, states)


class UNetFire(nn.Module):
    def __init__(self, num_bins, kind="convgru", base=16, num_res=2, norm=None, k=3, recurrent_res=(0,)):
        super().__init__()
        self.head = RecurrentConvLayer(num_bins, base, k, 1, k // 2, kind, norm)
        self.recurrent_res = tuple(i for i in range(num_res) if i in recurrent_res or -1 in recurrent_res)
        self.resblocks = nn.ModuleList(
            RecurrentResidualLayer(base, kind, norm) if i in self.recurrent_res else ResidualBlock(base, norm)
            for i in range(int(num_res)))
        self.pred = ConvLayer(base, 1, 1, relu=False, norm=None)

    def forward(self, x, states=None):
        rec = [self.head] + [self.resblocks[i] for i in self.recurrent_res]
        per = iter(_split_states(states, rec))
        x, new_states = self.head(x, next(per))
        new_states = list(new_states)
        for i, rb in enumerate(self.resblocks):
            if i in self.recurrent_res:
                x, s = rb(x, next(per))
                new_states.extend(s)
            else:
                x = rb(x)
        return self.pred(x), new_states


class FireNet(nn.Module):
    """FireNet: ``forward(voxel (N, B, H, W), states) -> (image, states)``; the raw output is
    unbounded (the engine clips it to [0, 1]); any H, W."""

    size_multiple = 1

    def __init__(self, config: dict | None = None):
        super().__init__()
        c = dict(FIRENET_RELEASED_CONFIG, **(config or {}))
        self.config = c
        self.num_bins = int(c["num_bins"])
        if c.get("skip_type", "no_skip") == "concat":
            raise ValueError("FireNet with skip_type 'concat' is not supported")
        rb = c.get("recurrent_blocks") or {}
        self.net = UNetFire(self.num_bins, c["recurrent_block_type"], int(c["base_num_channels"]),
                            int(c["num_residual_blocks"]), _check_norm(c.get("norm")), int(c["kernel_size"]),
                            tuple(int(i) for i in rb.get("resblock", [])))

    def forward(self, x, states=None):
        return self.net(x, states)


ARCHS = {"E2VIDRecurrent": E2VIDRecurrent, "FireNet": FireNet}


def build_network(arch: str, config: dict | None = None) -> nn.Module:
    """A network by the checkpoint's ``arch`` name ("E2VIDRecurrent" or "FireNet")."""
    if arch not in ARCHS:
        raise ValueError(f"unsupported architecture {arch!r}; expected one of {sorted(ARCHS)}")
    return ARCHS[arch](config)
