"""Learned events-only baselines: E2VID (Rebecq et al., TPAMI 2019) and FireNet (Scheerlinck et
al., WACV 2020), run from the authors' released checkpoints (never downloaded).

``reconstruct(rec, "e2vid", {"weights": "E2VID_lightweight.pth.tar"})``. Each output time t
gets the network's image for the events in [previous output time, t) (fixed-duration windows,
the first one starting at the first event), as a 5-bin voxel grid normalised per window; the
recurrent state carries over from window to window and starts from zeros for every recording.
Output: a relative intensity in [0, 1] (E2VID: its sigmoid output; FireNet: its output clipped
to [0, 1]), the display-referred scale of the networks' training frames, not calibrated
radiance. PyTorch (``hybridhdr[learned]``) is imported only when a network runs.
"""

from .params import WEIGHTS_HELP, E2VIDParams, FireNetParams, LearnedParams, WeightsRequiredError
from .voxel import events_to_voxel_grid, normalize_voxel_grid

__all__ = ["E2VIDParams", "FireNetParams", "LearnedParams", "WEIGHTS_HELP", "WeightsRequiredError",
           "events_to_voxel_grid", "normalize_voxel_grid", "LearnedEngine", "LEARNED_METHODS"]

LEARNED_METHODS = ("e2vid", "firenet")


def __getattr__(name):
    if name in ("LearnedEngine", "Reconstructor", "load_network", "load_checkpoint", "export_onnx"):
        from . import engine
        return getattr(engine, name)
    raise AttributeError(name)
