"""Sets of cameras: which kind of capture they make, and whether two sets are one.

:func:`capture_kind` tells a forward-facing capture from a 360° one by the spread of the
optical axes (``process`` decides photos by it, the LLFF loader a ``poses_bounds.npy``).
The same photos posed twice (a dataset's two pose files, or recovered poses against published
ones) are compared after a similarity alignment: :func:`umeyama` fits the similarity ``x -> s R x + t`` between matched points (Umeyama 1991,
least squares with the reflection guard); :func:`same_cameras` says whether two camera sets
are one set up to such a similarity: centres within ``centre_tol`` of their spread and
orientations within ``rot_tol_deg`` after the fit.
"""

from __future__ import annotations

import numpy as np

__all__ = ["capture_kind", "FORWARD_THRESHOLD", "umeyama", "same_cameras"]

FORWARD_THRESHOLD = 0.9
"""A capture is forward-facing when ``|mean unit forward axis| >= FORWARD_THRESHOLD`` (every
optical axis within ~25° of their mean), else 360° (an object seen from around it)."""


def capture_kind(c2w: np.ndarray) -> str:
    """``"forward"`` or ``"360"`` of OpenGL cameras ``c2w [N, 4, 4]`` by the spread of their
    optical axes (:data:`FORWARD_THRESHOLD`)."""
    fwd = -np.asarray(c2w, dtype=np.float64)[:, :3, 2]
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    return "forward" if np.linalg.norm(fwd.mean(0)) >= FORWARD_THRESHOLD else "360"


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity ``(s, R, t)`` minimising ``sum |s R src_i + t - dst_i|^2`` (``[N, 3]``)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1
    r = u @ d @ vt
    var = xs.var(0).sum()
    s = float(np.trace(np.diag(sig) @ d) / var) if var > 0 else 1.0
    return s, r, mu_d - s * r @ mu_s


def same_cameras(a: np.ndarray, b: np.ndarray, centre_tol: float = 0.01,
                 rot_tol_deg: float = 1.0) -> bool:
    """Whether OpenGL camera-to-world ``a, b [N, 4, 4]`` (matched by index, ``N >= 3``) are
    the same cameras up to a similarity: after :func:`umeyama` on the centres, every centre
    within ``centre_tol`` x the RMS spread of ``b``'s centres and every orientation within
    ``rot_tol_deg`` degrees."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim != 3 or len(a) < 3:
        return False
    s, r, t = umeyama(a[:, :3, 3], b[:, :3, 3])
    centres = s * a[:, :3, 3] @ r.T + t
    spread = np.sqrt(((b[:, :3, 3] - b[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    if not spread > 0 or np.linalg.norm(centres - b[:, :3, 3], axis=1).max() > centre_tol * spread:
        return False
    cos = (np.einsum("nij,nij->n", r @ a[:, :3, :3], b[:, :3, :3]) - 1) / 2
    return bool(np.degrees(np.arccos(np.clip(cos, -1, 1))).max() <= rot_tol_deg)
