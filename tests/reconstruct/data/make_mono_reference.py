"""Regenerates mono_reference.npz: every method's output on a small procedural recording (grey and
colour frames, no CFA), written at commit a6507ee (threshold maps), before the colour path existed.
The two-sided AKF entries (``*_akf_offline*``) were recomputed when the fusion gained the carried
frame's variance (AKFParams.fusion_carried_variance) and again when the fusion's exp became
numpy's float32 exp, as the forward outputs' (changes below 2.3e-7 relative), and again (grey
frames: 803 of 4800 values, below 6.1e-5 relative) when a frame that clips a pixel stopped
restarting that pixel's carried variance; every other entry is the original.

Run ``python tests/reconstruct/data/make_mono_reference.py tests/reconstruct/data/mono_reference.npz``
only when a deliberate change of the monochrome results is made."""
import numpy as np, hashlib, sys
from hybridhdr.simulate.procedural import procedural_recording
from hybridhdr.reconstruct import reconstruct
from hybridhdr.model import Frames, Recording
import dataclasses

def recordings():
    rec, _ = procedural_recording((12, 16), 300_000, seed=3, step_us=500)
    f = rec.frames
    rgb = np.stack([f.images, np.roll(f.images, 1, axis=2), f.images // 2], axis=-1)
    rec_rgb = dataclasses.replace(rec, frames=Frames(rgb, f.t_start_us, f.t_end_us, encoding="gamma"))
    return rec, rec_rgb

RUNS = [("akf", "offline", {}), ("akf", "causal", {}), ("akf", "forward", {}), ("akf", "offline", {"augment": True}),
        ("cf", "offline", {}), ("direct", "offline", {}), ("highpass", "offline", {}), ("frames_zoh", "offline", {}),
        ("frames_linear", "offline", {}), ("edi", "offline", {})]

if __name__ == "__main__":
    rec, rec_rgb = recordings()
    out = {}
    for name, r in (("grey", rec), ("rgb", rec_rgb)):
        for m, mode, kw in RUNS:
            v = reconstruct(r, m, mode=mode, fps=100, **kw)
            key = f"{name}_{m}_{mode}" + ("_aug" if kw else "")
            out[key] = v.frames
            out[key + "_t"] = v.t_us
            print(key, v.frames.shape, hashlib.sha256(v.frames.tobytes()).hexdigest()[:12])
    np.savez_compressed(sys.argv[1], **out)
