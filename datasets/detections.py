"""The detection records: one JSON schema for every detector's output, 3D and 2D alike
(docs/formats.md), what `spherebench detect` and `detect-2d` print, one line per input or frame.
"""

from __future__ import annotations

from spherebench.circles import circle_bbox


def detection_record(score: float, circle_px=None, centre_m=None, radius_m: float | None = None,
                     inliers: int | None = None, visible_fraction: float | None = None,
                     raw_score: float | None = None) -> dict:
    """One detection: score (the 3D detector's: the probability that it is a ball within 2 cm; a 2D
    detector's own confidence); circle_px {center [cx, cy], radius} px (None: it projects nowhere on
    the image) with its COCO bbox [x, y, w, h] px; center_m [x, y, z] and radius_m, metres, camera
    frame (None from a 2D detector); inliers, the points on the sphere, and visible_fraction, the
    share of its silhouette no nearer surface hides (None from a 2D detector or an unorganised cloud);
    raw_score, the 3D detector's evidence product that the score is mapped from (None from a 2D detector)."""
    circle = None if circle_px is None else [float(v) for v in circle_px[:3]]
    return {"score": round(float(score), 6),
            "center_m": None if centre_m is None else [round(float(v), 6) for v in centre_m],
            "radius_m": None if radius_m is None else round(float(radius_m), 6),
            "circle_px": None if circle is None else {"center": [round(circle[0], 3), round(circle[1], 3)],
                                                      "radius": round(circle[2], 3)},
            "bbox": None if circle is None else circle_bbox(*circle, decimals=3),
            "inliers": None if inliers is None else int(inliers),
            "visible_fraction": None if visible_fraction is None else round(float(visible_fraction), 3),
            "raw_score": None if raw_score is None else round(float(raw_score), 6)}


def frame_record(source: str, detections: list[dict], ms: float, frame: int | None = None,
                 timestamp_ms: float | None = None, **extra) -> dict:
    """One input's (or one stream frame's) line: source, frame number and timestamp (ms; None for a
    file), detections (``detection_record``s, best first), ms (the detection alone), and any extra
    fields of the command (e.g. radius_m)."""
    return {"input": str(source), "frame": None if frame is None else int(frame),
            "timestamp_ms": None if timestamp_ms is None else round(float(timestamp_ms), 3),
            **extra, "detections": detections, "ms": round(float(ms), 3)}


def track_record(track_id: int, confirmed: bool, centre_m, velocity_m_s, probability: float,
                 radius_m: float | None, detection: int | None, radius_se_m: float | None = None,
                 reported: bool | None = None) -> dict:
    """One track after a frame (``detect --track``): its id, whether it is confirmed, its filtered
    center_m [x, y, z] (m) and velocity_m_s [vx, vy, vz] (m/s), camera frame, its probability (the
    fused evidence that it is the ball), its radius_m (the mean of its detections' free radii; None
    where none was measured) and that mean's standard error radius_se_m (None below two), and the
    index in the frame's detections of the one it took (None: it took none this frame), and whether
    the tracker answers with it in this frame (confirmed, or a new ball's detection of this frame)."""
    return {"track_id": int(track_id), "confirmed": bool(confirmed),
            "center_m": [round(float(v), 6) for v in centre_m],
            "velocity_m_s": [round(float(v), 4) for v in velocity_m_s],
            "probability": round(float(probability), 6),
            "radius_m": None if radius_m is None else round(float(radius_m), 6),
            "radius_se_m": None if radius_se_m is None else round(float(radius_se_m), 6),
            "detection": None if detection is None else int(detection),
            "reported": bool(confirmed) if reported is None else bool(reported)}
