"""Rendering a synthetic photo: the scene seen by a posed camera (markers anti-aliased, their exact
pixels recorded), blur, glare, noise and vignetting, written as a maker's JPEG with EXIF and XMP."""

from __future__ import annotations

import datetime as dt
import io
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from geoortho.core.camera import Intrinsics, Pose, pixel_rays, project_points
from geoortho.core.outputs import atomic_path
from geoortho.core.surface import GridSurface, RayHits
from geoortho.gcp.blur import motion_kernel, spread_path
from geoortho.gcp.markers import (
    target_half_extent,
)
from geoortho.synthetic.flight import Shot
from geoortho.synthetic.movers import draw_movers
from geoortho.synthetic.presets import (
    CAMERA_MODEL,
    EVEN_NOISE,
    FOCAL_35MM,
    FOCAL_MM,
    GRAIN_NOISE,
    GRAIN_PX,
    MAKER_MAKE,
    READ_NOISE,
    SHOT_NOISE_PER_LIGHT,
)
from geoortho.synthetic.scene import Marker, Scene

_SCENE: Scene | None = None


def init_render_worker(scene: Scene) -> None:
    global _SCENE
    _SCENE = scene
    cv2.setNumThreads(1)


def render_task(args: tuple[Shot, Intrinsics, bool, int, str, float, str, str, str, bool, str]) -> dict[str, Any]:
    shot, intr, hard, seed, path, glare, glare_style, blur_style, noise_style, pixels, vignetting_style = args
    assert _SCENE is not None
    return render_photo(
        _SCENE, shot, intr, hard=hard, seed=seed, path=Path(path), glare=glare, glare_style=glare_style,
        blur_style=blur_style, noise_style=noise_style, pixels=pixels, vignetting_style=vignetting_style,
    )  # fmt: skip


def render_photo(
    scene: Scene,
    shot: Shot,
    intr: Intrinsics,
    *,
    hard: bool,
    seed: int,
    path: Path | None,
    glare: float = 0.0,
    glare_style: str = "spot",
    blur_style: str = "exact",
    noise_style: str = "even",
    pixels: bool = True,
    vignetting_style: str = "quadratic",
) -> dict[str, Any]:
    """Render one photo (and write it when ``path`` is given); return its marker truth.

    ``pixels`` False: only the markers' windows are cast and drawn, on flat grey, with no
    camera effects; the marker truth is the same."""
    rng = np.random.default_rng(seed)
    pose = Pose.from_ypr((shot.x, shot.y, shot.z), shot.yaw_deg, shot.pitch_deg, shot.roll_deg)
    w, h = intr.width_px, intr.height_px
    surf = scene.surface

    def cast(cols: np.ndarray, rows: np.ndarray) -> RayHits:
        rays = pixel_rays(np.c_[cols.ravel(), rows.ravel()], intr, pose)
        return surf.intersect(pose.center, rays, max_range_m=2000.0, step_m=0.6)

    if not pixels:
        img = np.full((h, w, 3), 0.5, np.float32)

        def hits_in(y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
            cols, rows = np.meshgrid(np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64))
            return cast(cols, rows).points.reshape(y1 - y0 + 1, x1 - x0 + 1, 3)

        markers = _marker_truth_and_antialias(scene, shot, intr, pose, img, hits_in)
        if path is not None:
            _write_jpeg(path, _to_bytes(img), shot, intr)
        return {"image": shot.name, "markers": markers, "blur_px": shot.blur_px, "blur_deg": 0.0}
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    hits = cast(uu, vv)
    pts = hits.points
    rgb = np.full((len(pts), 3), (0.75, 0.80, 0.88), np.float32)  # sky / off-scene haze
    good = hits.hit
    rgb[good] = scene.color(pts[good, 0], pts[good, 1], pts[good, 2])
    img = rgb.reshape(h, w, 3)
    grid_pts = pts.reshape(h, w, 3)
    if scene.movers:
        depth = np.where(good, (pts - pose.center) @ pose.rotation[:, 2], np.nan).reshape(h, w)
        ground = GridSurface(scene.dtm, scene.transform, scene.crs).elevation
        draw_movers(img, list(scene.movers), _seconds_of_day(shot), intr, pose, ground, depth)
    markers = _marker_truth_and_antialias(
        scene, shot, intr, pose, img, lambda y0, y1, x0, x1: grid_pts[y0 : y1 + 1, x0 : x1 + 1]
    )

    # Camera effects: vignetting, exposure, glare, blur, noise.
    r2 = ((uu - intr.cx_px) ** 2 + (vv - intr.cy_px) ** 2) / (intr.cx_px**2 + intr.cy_px**2)
    img = img * vignetting(r2, vignetting_style)[..., None].astype(np.float32) * shot.exposure_gain
    # effects asked for by option draw from their own stream: the rest of the photo stays as without them
    opt = np.random.default_rng([seed, 1])
    for m in markers:
        if not m["inside"]:
            continue
        if hard and rng.random() < 0.3:  # sun glare on the marker
            gx, gy = m["x_px"] + rng.normal(0, 4), m["y_px"] + rng.normal(0, 4)
            amp, sigma = 0.45, m["size_px"] * 0.35
        elif not hard and glare > 0 and opt.random() < glare:
            img = img + _glare(opt, glare_style, m["x_px"], m["y_px"], m["size_px"], uu, vv)[..., None]
            m["glare"] = True
            continue
        else:
            continue
        g = np.exp(-((uu - gx) ** 2 + (vv - gy) ** 2) / (2 * sigma**2))
        img = img + amp * g[..., None].astype(np.float32)
        m["glare"] = True
    blur_deg = 0.0
    if shot.blur_px > 0:
        blur_deg = float(rng.uniform(0, 180) if hard else opt.uniform(0, 180))
        kernel = (
            motion_kernel(shot.blur_px, blur_deg)
            if hard or blur_style == "exact"
            else _other_motion_kernel(shot.blur_px, blur_deg, blur_style, opt)
        )
        img = np.asarray(cv2.filter2D(img, -1, kernel), np.float32)
    img = img + sensor_noise(rng, noise_style, img)
    if path is not None:
        _write_jpeg(path, _to_bytes(img), shot, intr)
    return {"image": shot.name, "markers": markers, "blur_px": shot.blur_px, "blur_deg": blur_deg}


def vignetting(rho: np.ndarray, style: str = "quadratic") -> np.ndarray:
    """The share of the centre's light a photo keeps at ``rho`` (the squared radius over the
    half-diagonal's), as ``style`` draws it (:data:`VignettingStyle`)."""
    rho = np.asarray(rho, np.float64)
    if style == "cos4":
        return np.asarray(np.cos(np.arctan(np.sqrt(rho) * math.tan(math.radians(25.0)))) ** 4)
    if style == "flat-drop":
        return np.asarray(np.exp(-0.14 * rho**2))
    return 1.0 - 0.25 * rho


def _seconds_of_day(shot: Shot) -> float:
    """The shot's exposure time, seconds after its day's midnight (0 without a time)."""
    if not shot.time:
        return 0.0
    stamp = dt.datetime.strptime(shot.time, "%Y:%m:%d %H:%M:%S")
    return stamp.hour * 3600.0 + stamp.minute * 60.0 + stamp.second + int(shot.subsec or 0) / 1000.0


def _to_bytes(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def sensor_noise(rng: np.random.Generator, style: str, img: np.ndarray) -> np.ndarray:
    """The noise of ``style`` (:data:`NoiseStyle`) to add to a rendered photo (h, w, 3; 1.0 =
    white), drawn from ``rng``."""
    if style == "shot":
        sigma = np.sqrt(SHOT_NOISE_PER_LIGHT * np.clip(img, 0.0, None) + READ_NOISE**2)
        result: np.ndarray = (rng.standard_normal(img.shape) * sigma).astype(np.float32)
        return result
    if style == "grain":
        # white noise smoothed over a couple of pixels, each channel its own (coloured blotches),
        # scaled back to its spread
        raw = rng.standard_normal(img.shape).astype(np.float32)
        smooth = cv2.GaussianBlur(raw, (0, 0), GRAIN_PX, borderType=cv2.BORDER_REFLECT)
        result = smooth * np.float32(GRAIN_NOISE / max(float(smooth.std()), 1e-9))
        return result
    return rng.normal(0, EVEN_NOISE, img.shape).astype(np.float32)


def _glare(
    rng: np.random.Generator, style: str, x_px: float, y_px: float, side_px: float, uu: np.ndarray, vv: np.ndarray
) -> np.ndarray:
    """One glare of ``style`` (:data:`GlareStyle`) near a target of ``side_px`` at (x, y): the light
    it adds to each pixel (1.0 = white)."""
    if style == "bloom":
        # a bloom 1.5-3 sides across, its core saturating, near the target
        gx, gy = x_px + rng.normal(0, 0.4) * side_px, y_px + rng.normal(0, 0.4) * side_px
        amp, sx = float(rng.uniform(0.8, 1.6)), side_px * float(rng.uniform(0.75, 1.5)) / 2.0
        sy, turn = sx, 0.0
    elif style == "sheen":
        # a soft veil, elongated and turned, that lifts the blacks without clipping
        gx, gy = x_px + rng.normal(0, 0.5) * side_px, y_px + rng.normal(0, 0.5) * side_px
        amp, sx = float(rng.uniform(0.25, 0.45)), side_px * float(rng.uniform(1.5, 2.5))
        sy, turn = sx / float(rng.uniform(2.0, 3.0)), float(rng.uniform(0, math.pi))
    else:
        # a specular spot, saturating part of the target
        gx, gy = x_px + rng.normal(0, 0.25) * side_px, y_px + rng.normal(0, 0.25) * side_px
        amp, sx = float(rng.uniform(0.5, 1.0)), side_px * float(rng.uniform(0.15, 0.3))
        sy, turn = sx, 0.0
    # only the pixels within 4 sigma: the photo is large, the glare is not
    reach = 4.0 * max(sx, sy)
    rows = slice(max(0, int(gy - reach)), max(0, int(gy + reach) + 1))
    cols = slice(max(0, int(gx - reach)), max(0, int(gx + reach) + 1))
    out = np.zeros(uu.shape, np.float32)
    du, dv = uu[rows, cols] - gx, vv[rows, cols] - gy
    a = du * math.cos(turn) + dv * math.sin(turn)
    b = -du * math.sin(turn) + dv * math.cos(turn)
    out[rows, cols] = amp * np.exp(-0.5 * ((a / sx) ** 2 + (b / sy) ** 2))
    return out


def _other_motion_kernel(length_px: float, angle_deg: float, style: str, rng: np.random.Generator) -> np.ndarray:
    """Motion blur drawn another way than :func:`motion_kernel`: ``line``, OpenCV's line rasteriser
    between whole-pixel ends (the length rounded); ``shake``, a curved path (a bow of up to a fifth
    of the length to one side) with a shutter that opens and closes gradually, centred on its mean:
    the pose is where the camera was on average over the exposure, which is where the smeared
    marker's image is (the bow's own centre put the markers' truth 0.52 px on average and up to
    1.4 px from any measure of them)."""
    r = int(math.ceil(length_px / 2)) + 2
    a = math.radians(angle_deg)
    if style == "line":
        img = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
        half = max(1, round(length_px)) / 2
        ends = [(round(r + s * half * math.cos(a)), round(r - s * half * math.sin(a))) for s in (-1, 1)]
        cv2.line(img, ends[0], ends[1], 1.0, 1, cv2.LINE_8)
        result: np.ndarray = img / img.sum()
        return result
    n = max(8, int(math.ceil(16 * length_px)))
    t = (np.arange(n) + 0.5) / n - 0.5
    bow = float(rng.uniform(-0.2, 0.2)) * length_px
    along, across = t * length_px, bow * (1 - 4 * t * t)
    x = r + along * math.cos(a) - across * math.sin(a)
    y = r - along * math.sin(a) - across * math.cos(a)
    weight = np.sin(np.pi * (t + 0.5)) ** 0.5  # the shutter's ramp
    # (bilinear spreading keeps a path's mean: the kernel's centroid is then its centre exactly)
    x += r - float(np.average(x, weights=weight))
    y += r - float(np.average(y, weights=weight))
    return spread_path(x, y, weight, 2 * r + 1)


def _marker_truth_and_antialias(
    scene: Scene,
    shot: Shot,
    intr: Intrinsics,
    pose: Pose,
    img: np.ndarray,
    hits_in: Callable[[int, int, int, int], np.ndarray],
) -> list[dict[str, Any]]:
    """Exact projected marker centres, and 4×4 supersampled marker pixels (markers lie on flat pads).

    ``hits_in(y0, y1, x0, x1)``: where the rays of those pixels (inclusive) meet the scene, (rows, cols, 3)."""
    s = scene.marker_size_m
    quiet = s * target_half_extent(scene.target, next(iter(scene.marker_cells.values()), None))
    h, w = img.shape[:2]
    out = []
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    for m in scene.markers:
        a = math.radians(m.angle_deg)
        ca, sa = math.cos(a), math.sin(a)

        def world(u: np.ndarray, v: np.ndarray, m: Marker = m, ca: float = ca, sa: float = sa) -> np.ndarray:
            result: np.ndarray = np.c_[m.x + u * ca + v * sa, m.y - u * sa + v * ca, np.full(len(u), m.z)]
            return result

        centre_px, depth = project_points(np.array([[m.x, m.y, m.z]]), intr, pose)
        if not np.isfinite(centre_px).all() or depth[0] <= 0:
            continue
        cx, cy = centre_px[0]
        corners = world(np.array([-s / 2, s / 2, s / 2, -s / 2]), np.array([s / 2, s / 2, -s / 2, -s / 2]))
        cpx, _ = project_points(corners, intr, pose)
        if not np.isfinite(cpx).all():
            continue
        margin = 2.0 * max(np.ptp(cpx[:, 0]), np.ptp(cpx[:, 1]))
        if not (-margin < cx < w + margin and -margin < cy < h + margin):
            continue
        inside = bool(((cpx[:, 0] >= 0) & (cpx[:, 0] <= w - 1) & (cpx[:, 1] >= 0) & (cpx[:, 1] <= h - 1)).all())
        # Occlusion: the ray to the centre must reach the pad.
        centre_visible = False
        if 0 <= cx <= w - 1 and 0 <= cy <= h - 1:
            p = hits_in(int(round(cy)), int(round(cy)), int(round(cx)), int(round(cx)))[0, 0]
            centre_visible = bool(abs(p[2] - m.z) < 0.1 and math.hypot(p[0] - m.x, p[1] - m.y) < s)
        qc = world(np.array([-quiet, quiet, quiet, -quiet]), np.array([quiet, quiet, -quiet, -quiet]))
        qpx, _ = project_points(qc, intr, pose)
        x0, x1 = int(max(0, np.floor(qpx[:, 0].min()) - 1)), int(min(w - 1, np.ceil(qpx[:, 0].max()) + 1))
        y0, y1 = int(max(0, np.floor(qpx[:, 1].min()) - 1)), int(min(h - 1, np.ceil(qpx[:, 1].max()) + 1))
        if x1 >= x0 and y1 >= y0:
            gu, gv = np.meshgrid(np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
            on_pad = np.abs(hits_in(y0, y1, x0, x1)[..., 2] - m.z) < 0.15
            su = (gu.ravel()[:, None, None] + sub[None, None, :]).repeat(4, 1)
            sv = (gv.ravel()[:, None, None] + sub[None, :, None]).repeat(4, 2)
            rays = pixel_rays(np.c_[su.ravel(), sv.ravel()], intr, pose)
            t = (m.z - pose.center[2]) / rays[:, 2]
            sp = pose.center + rays * t[:, None]
            col = scene.color(sp[:, 0], sp[:, 1], sp[:, 2]).reshape(-1, 16, 3).mean(axis=1)
            patch = img[y0 : y1 + 1, x0 : x1 + 1].reshape(-1, 3)
            mask = on_pad.ravel()
            patch[mask] = col[mask]
            img[y0 : y1 + 1, x0 : x1 + 1] = patch.reshape(y1 - y0 + 1, x1 - x0 + 1, 3)
        out.append(
            {
                "gcp": m.name,
                "marker_id": m.marker_id,
                "decoy": m.decoy,
                "x_px": float(cx),
                "y_px": float(cy),
                "corners_px": cpx.tolist(),
                "inside": inside and centre_visible,
                "in_frame": inside,
                "occluded": not centre_visible and 0 <= cx <= w - 1 and 0 <= cy <= h - 1,
                "size_px": float(np.sqrt(abs(cv2.contourArea(cpx.astype(np.float32))))),
                "glare": False,
            }
        )
    return out


def _dms(value: float) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    v = abs(value)
    d = int(v)
    m = int((v - d) * 60)
    s = (v - d - m / 60) * 3600
    return (d, 1), (m, 1), (int(round(s * 1_000_000)), 1_000_000)


def _xmp(shot: Shot) -> bytes:
    """The photo's XMP packet as its maker writes it (``shot.maker``)."""
    make = MAKER_MAKE[shot.maker]
    ns = {
        "dji": 'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"',
        "autel": 'xmlns:drone="http://www.autelrobotics.cn/drone/1.0/"',
        "parrot": 'xmlns:drone-parrot="http://www.parrot.com/drone-parrot/1.0/" '
        'xmlns:Camera="http://pix4d.com/camera/1.0/"',
        "skydio": 'xmlns:drone-skydio="https://www.skydio.com/drone-skydio/1.0/"',
        "pix4d": 'xmlns:Camera="http://pix4d.com/camera/1.0/"',
        "sensefly": 'xmlns:Camera="http://ns.sensefly.com/Camera/1.0/"',
    }[shot.maker]
    attitude, body = _xmp_attitude(shot)
    attrs = _xmp_accuracy(shot) + _xmp_calibration(shot) + attitude
    return (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        f'  <rdf:Description rdf:about="{make} Meta Data"\n'
        f'    xmlns:tiff="http://ns.adobe.com/tiff/1.0/" {ns}\n'
        f'    tiff:Make="{make}" tiff:Model="{CAMERA_MODEL}"\n' + attrs + "  >\n" + body + "  </rdf:Description>\n"
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        '<?xpacket end="w"?>'
    ).encode()


def _xmp_signed(v: float) -> str:
    return f"{v:+.2f}"


def _xmp_optional(name: str, v: float) -> str:
    """An attribute line, or nothing for a value not recorded (NaN)."""
    return f'    {name}="{_xmp_signed(v)}"\n' if math.isfinite(v) else ""


def _xmp_accuracy(shot: Shot) -> str:
    """The position's stated accuracy, as each maker writes it (m, to the millimetre: a receiver's
    centimetres need it); nothing without an RTK flag."""
    if shot.rtk_flag < 0:
        return ""
    if shot.maker in ("dji", "autel"):
        p = "drone-dji" if shot.maker == "dji" else "drone"
        return (
            f'    {p}:RtkFlag="{shot.rtk_flag}"\n'
            f'    {p}:RtkStdLon="{shot.rtk_sigma_h_m:.4f}"\n'
            f'    {p}:RtkStdLat="{shot.rtk_sigma_h_m * 0.9:.4f}"\n'
            f'    {p}:RtkStdHgt="{shot.rtk_sigma_v_m:.4f}"\n'
        )
    if shot.maker in ("pix4d", "sensefly", "parrot"):
        return (
            f'    Camera:GPSXYAccuracy="{shot.rtk_sigma_h_m:.4f}"\n    Camera:GPSZAccuracy="{shot.rtk_sigma_v_m:.4f}"\n'
        )
    return ""


def _xmp_calibration(shot: Shot) -> str:
    """DJI's factory calibration (focal length, optical centre, DewarpData), when the shot has one."""
    if shot.maker != "dji" or not math.isfinite(shot.cal_focal_px):
        return ""
    return (
        f'    drone-dji:CalibratedFocalLength="{shot.cal_focal_px:.6f}"\n'
        f'    drone-dji:CalibratedOpticalCenterX="{shot.cal_cx_px:.6f}"\n'
        f'    drone-dji:CalibratedOpticalCenterY="{shot.cal_cy_px:.6f}"\n'
        f'    drone-dji:DewarpData="2026-05-01;{shot.cal_focal_px:.6f},{shot.cal_focal_px:.6f},0.000000,0.000000,'
        + ",".join(f"{v:.9f}" for v in shot.cal_distortion)
        + '"\n    drone-dji:DewarpFlag="0"\n'
    )


def _xmp_attitude(shot: Shot) -> tuple[str, str]:
    """Heights and angles as each maker writes them: (attribute lines, element lines)."""
    f, opt = _xmp_signed, _xmp_optional
    if shot.maker in ("dji", "autel"):
        p = "drone-dji" if shot.maker == "dji" else "drone"
        absolute = (
            f'    {p}:AbsoluteAltitude="{shot.rec_abs_alt_m:+.3f}"\n'
            if shot.rtk_flag >= 0 and math.isfinite(shot.rec_abs_alt_m)
            else opt(f"{p}:AbsoluteAltitude", shot.rec_abs_alt_m)
        )
        return (
            absolute
            + opt(f"{p}:RelativeAltitude", shot.rec_rel_alt_m)
            + opt(f"{p}:GimbalRollDegree", shot.rec_roll_deg)
            + opt(f"{p}:GimbalYawDegree", shot.rec_yaw_deg)
            + opt(f"{p}:GimbalPitchDegree", shot.rec_pitch_deg)
            + opt(f"{p}:FlightRollDegree", shot.flight_roll_deg)
            + opt(f"{p}:FlightYawDegree", shot.flight_yaw_deg)
            + opt(f"{p}:FlightPitchDegree", shot.flight_pitch_deg)
        ), ""
    if shot.maker == "parrot":
        # Parrot writes its NED angles and the same attitude in Pix4D's Camera: convention.
        return "", (
            f"   <drone-parrot:CameraRollDegree>{f(shot.rec_roll_deg)}</drone-parrot:CameraRollDegree>\n"
            f"   <drone-parrot:CameraPitchDegree>{f(shot.rec_pitch_deg)}</drone-parrot:CameraPitchDegree>\n"
            f"   <drone-parrot:CameraYawDegree>{f(shot.rec_yaw_deg)}</drone-parrot:CameraYawDegree>\n"
            f"   <Camera:Roll>{f(shot.rec_roll_deg)}</Camera:Roll>\n"
            f"   <Camera:Pitch>{f(shot.rec_pitch_deg + 90.0)}</Camera:Pitch>\n"
            f"   <Camera:Yaw>{f(shot.rec_yaw_deg)}</Camera:Yaw>\n"
            + (
                f"   <Camera:AboveGroundAltitude>{f(shot.rec_rel_alt_m)}</Camera:AboveGroundAltitude>\n"
                if math.isfinite(shot.rec_rel_alt_m)
                else ""
            )
        )
    if shot.maker == "skydio":
        # Several frames share the field names: the camera's is CameraOrientationNED (a struct),
        # written after a body-frame struct that must not be taken for it.
        return opt("drone-skydio:AbsoluteAltitude", shot.rec_abs_alt_m) + opt(
            "drone-skydio:RelativeAltitude", shot.rec_rel_alt_m
        ), (
            '   <drone-skydio:CameraOrientationFLU rdf:parseType="Resource">\n'
            "    <drone-skydio:Yaw>+12.00</drone-skydio:Yaw><drone-skydio:Pitch>+3.00</drone-skydio:Pitch>"
            "<drone-skydio:Roll>+1.00</drone-skydio:Roll>\n"
            "   </drone-skydio:CameraOrientationFLU>\n"
            '   <drone-skydio:CameraOrientationNED rdf:parseType="Resource">\n'
            f"    <drone-skydio:Yaw>{f(shot.rec_yaw_deg)}</drone-skydio:Yaw>\n"
            f"    <drone-skydio:Pitch>{f(shot.rec_pitch_deg)}</drone-skydio:Pitch>\n"
            f"    <drone-skydio:Roll>{f(shot.rec_roll_deg)}</drone-skydio:Roll>\n"
            "   </drone-skydio:CameraOrientationNED>\n"
        )
    # pix4d, sensefly
    roll = -shot.rec_roll_deg if shot.maker == "sensefly" else shot.rec_roll_deg
    return (
        opt("Camera:Yaw", shot.rec_yaw_deg)
        + opt("Camera:Pitch", shot.rec_pitch_deg + 90.0)
        + opt("Camera:Roll", roll)
        + opt("Camera:AboveGroundAltitude", shot.rec_rel_alt_m)
    ), ""


def _write_jpeg(path: Path, pixels: np.ndarray, shot: Shot, intr: Intrinsics) -> None:
    import piexif
    from PIL import Image

    zeroth = {
        piexif.ImageIFD.Make: MAKER_MAKE[shot.maker].encode(),
        piexif.ImageIFD.Model: CAMERA_MODEL.encode(),
        piexif.ImageIFD.Orientation: 1,
        piexif.ImageIFD.Software: b"geoortho.synth",
        piexif.ImageIFD.DateTime: shot.time.encode(),
    }
    exif = {
        piexif.ExifIFD.DateTimeOriginal: shot.time.encode(),
        **({piexif.ExifIFD.SubSecTimeOriginal: shot.subsec.encode()} if shot.subsec else {}),
        piexif.ExifIFD.FocalLength: (int(round(shot.exif_focal_mm * 100)), 100),
        piexif.ExifIFD.FocalLengthIn35mmFilm: int(round(FOCAL_35MM * shot.exif_focal_mm / FOCAL_MM)),
        piexif.ExifIFD.PixelXDimension: intr.width_px,
        piexif.ExifIFD.PixelYDimension: intr.height_px,
        piexif.ExifIFD.ExposureTime: (int(round(shot.exposure_time_s * 1e6)), 1_000_000),
        piexif.ExifIFD.FNumber: (28, 10),
        piexif.ExifIFD.ISOSpeedRatings: 100,
    }
    gps: dict[int, Any] = {}
    if shot.has_gps:
        gps = {
            piexif.GPSIFD.GPSVersionID: (2, 3, 0, 0),
            piexif.GPSIFD.GPSLatitudeRef: b"N" if shot.rec_lat >= 0 else b"S",
            piexif.GPSIFD.GPSLatitude: _dms(shot.rec_lat),
            piexif.GPSIFD.GPSLongitudeRef: b"E" if shot.rec_lon >= 0 else b"W",
            piexif.GPSIFD.GPSLongitude: _dms(shot.rec_lon),
            piexif.GPSIFD.GPSAltitudeRef: 0 if shot.rec_gps_alt_m >= 0 else 1,
            piexif.GPSIFD.GPSAltitude: (int(round(abs(shot.rec_gps_alt_m) * 1000)), 1000),
        }
        if shot.maker == "exif" and shot.has_attitude:  # no XMP: where the image top points, true north
            gps[piexif.GPSIFD.GPSImgDirectionRef] = b"T"
            gps[piexif.GPSIFD.GPSImgDirection] = (int(round(shot.rec_yaw_deg % 360.0 * 100)), 100)
    exif_bytes = piexif.dump({"0th": zeroth, "Exif": exif, "GPS": gps})
    buf = io.BytesIO()
    kwargs: dict[str, Any] = {"exif": exif_bytes, "quality": 92}
    if shot.has_xmp and shot.maker != "exif":
        kwargs["xmp"] = _xmp(shot)
    Image.fromarray(pixels).save(buf, format="JPEG", **kwargs)
    data = buf.getvalue()
    if shot.corrupt:
        data = data[: len(data) // 3]  # truncated mid-scan, as an interrupted copy leaves it
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
