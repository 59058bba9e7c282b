"""The fixed-shape training step against the cpu preset's waves on lego 400², equal steps and
sample budget (2^17): validation PSNR on 3 test views after 300 steps, wall seconds, rays per
step and samples per ray of the last log row. A quality check of issue 47's fixed step on the
CPU (its GPU speed is not measured here).

Usage: ``python benchmarks/fixed_vs_waves.py`` (~4 minutes on 2 cores; paths of this
project's data folder).
"""
import sys, shutil, time, json
from pathlib import Path
from plenoctree.nerf import preset, train
res = {}
for fixed in (False, True):
    out = Path(f"/tmp/sk/lego_fixed{int(fixed)}"); shutil.rmtree(out, ignore_errors=True)
    cfg = preset("cpu")
    cfg.data, cfg.out, cfg.downscale = "/work/shared/data/nerf_synthetic/lego", str(out), 2
    cfg.max_steps, cfg.val_views, cfg.val_every_s, cfg.preview_every_s = 300, 3, 0.0, 0.0
    cfg.fixed_step = fixed
    t = time.time(); r = train(cfg, quiet=True)
    res[fixed] = (round(time.time() - t, 1), round(r.val_psnr, 3), r.log["train"][-1]["rays"], r.log["train"][-1]["samples_per_ray"])
    print(fixed, res[fixed], flush=True)
