"""Ground truth for recorded traverses: positions at frame times -> admissible references.

Field datasets give the vehicle's position at its own timestamps (GPS fixes, an INS pose
stream); event frames have their own times (window ``k`` from :func:`window_times`). The
position of each frame is interpolated linearly in time, and a reference frame is an
admissible match for a query frame when their positions lie within a distance:

    t_ref = window_times(origin_ref, 10_000, R)          # us, sensor clock of the reference
    gt = ground_truth_within(positions_at(t_ref, ref_t, ref_pos),
                             positions_at(t_qry, qry_t, qry_pos), radius=10.0)   # (R, Q)

GPS latitude/longitude become metres with :func:`geodetic_to_ecef` (WGS84, exact), so that
distances are Euclidean.
"""

from __future__ import annotations

import numpy as np

from torchseq.ground_truth import GroundTruthError

WGS84_A = 6_378_137.0
WGS84_E2 = 6.694_379_990_14e-3


def window_times(origin_us: int, window_us: int, n_windows: int,
                 at: str = "centre") -> np.ndarray:
    """``(T,)`` float64 sensor time of each window: its ``"start"``, ``"centre"`` or ``"end"``.

    Window ``k`` covers ``[origin + k * window_us, origin + (k + 1) * window_us)`` (see
    :func:`torchseq.events.frames.window_origin` for the origin of an anchor).
    """
    shift = {"start": 0.0, "centre": 0.5, "end": 1.0}
    if at not in shift:
        raise ValueError(f"at must be one of {sorted(shift)}, got {at!r}")
    if window_us <= 0 or n_windows < 0:
        raise ValueError("window_us must be > 0 and n_windows >= 0")
    return origin_us + (np.arange(n_windows) + shift[at]) * float(window_us)


def positions_at(times_us, pose_times_us, positions) -> np.ndarray:
    """Positions at ``times_us`` by linear interpolation between timed positions.

    Args:
        times_us: ``(T,)`` query times (same clock and unit as ``pose_times_us``).
        pose_times_us: ``(N,)`` strictly increasing times of the positions.
        positions: ``(N, D)`` positions (metres, or route units).

    Returns:
        ``(T, D)`` float64; rows of times outside ``[pose_times[0], pose_times[-1]]`` are
        NaN (no position: never an admissible match).
    """
    t = np.asarray(times_us, dtype=np.float64).reshape(-1)
    pt = np.asarray(pose_times_us, dtype=np.float64).reshape(-1)
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim == 1:
        pos = pos[:, None]
    if pos.ndim != 2 or len(pos) != len(pt) or len(pt) < 1:
        raise GroundTruthError(f"positions {pos.shape} do not match {len(pt)} pose times")
    if not (np.isfinite(pt).all() and np.isfinite(pos).all() and np.isfinite(t).all()):
        raise GroundTruthError("pose times, positions and frame times must be finite")
    if len(pt) > 1 and (np.diff(pt) <= 0).any():
        raise GroundTruthError("pose times must increase strictly")
    out = np.stack([np.interp(t, pt, pos[:, d]) for d in range(pos.shape[1])], axis=1)
    out[(t < pt[0]) | (t > pt[-1])] = np.nan
    return out


def geodetic_to_ecef(lat_deg, lon_deg, alt_m=0.0) -> np.ndarray:
    """``(N, 3)`` Earth-centred Earth-fixed metres from WGS84 latitude, longitude, altitude."""
    lat, lon = np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float))
    alt = np.broadcast_to(np.asarray(alt_m, float), lat.shape)
    if not (np.isfinite(lat).all() and np.isfinite(lon).all() and np.isfinite(alt).all()):
        raise GroundTruthError("latitude, longitude and altitude must be finite")
    if (np.abs(lat) > np.pi / 2 + 1e-12).any():
        raise GroundTruthError("latitude outside -90..90 degrees")
    n = WGS84_A / np.sqrt(1 - WGS84_E2 * np.sin(lat) ** 2)
    return np.stack([(n + alt) * np.cos(lat) * np.cos(lon), (n + alt) * np.cos(lat) * np.sin(lon),
                     (n * (1 - WGS84_E2) + alt) * np.sin(lat)], axis=-1).reshape(-1, 3)


def ground_truth_within(reference_positions, query_positions, radius: float) -> np.ndarray:
    """``(R, Q)`` bool: reference ``i`` within ``radius`` of query ``j`` (NaN rows: never).

    Args:
        reference_positions: ``(R, D)`` (or ``(R,)``) positions of the reference frames.
        query_positions: ``(Q, D)`` positions of the query frames, same units.
        radius: admissible distance (>= 0).
    """
    ref = np.asarray(reference_positions, np.float64)
    qry = np.asarray(query_positions, np.float64)
    ref, qry = (a[:, None] if a.ndim == 1 else a for a in (ref, qry))
    if ref.ndim != 2 or qry.ndim != 2 or ref.shape[1] != qry.shape[1]:
        raise GroundTruthError(f"positions {ref.shape} and {qry.shape} do not match")
    if not radius >= 0:
        raise GroundTruthError(f"radius must be >= 0, got {radius}")
    out = np.zeros((len(ref), len(qry)), bool)
    for q0 in range(0, len(qry), 1024):  # bounded (R, 1024, D) temporaries
        d = np.sqrt(((ref[:, None, :] - qry[None, q0:q0 + 1024, :]) ** 2).sum(-1))
        out[:, q0:q0 + 1024] = d <= radius  # NaN compares False
    return out
