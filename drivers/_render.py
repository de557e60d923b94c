"""Rasteriser for the simulated rover: textured planar surfaces into rectified pinhole images.

Each visible surface is clipped to the view frustum's near plane and cut into depth bands; each
band is drawn by warping the texture with the plane's homography (cv2.warpPerspective restricted
to the band's bounding box) and composited with a depth test. For a plane n·X = d in the camera
frame, a pixel (x, y) sees the point X = Z K⁻¹(x, y, 1)ᵀ, so 1/Z = n·K⁻¹(x, y, 1)ᵀ / d is affine
in the pixel coordinates: the depth buffer stores 1/Z [1/m] and is filled analytically, no
per-pixel ray casting. Depth bands let a long surface use a coarser mip level far away
(minification without aliasing) and a sharp one close by. A surface with a coverage mask
(``Surface.alpha``) is drawn only where the mask is set (a tree crown's outline).

Camera optical frame: x right, y down, z forward (robotd.core.geometry); pixel centres at integers.
"""

from __future__ import annotations

import math

import cv2
import numba as nb
import numpy as np

from drivers.simbase import Surface

Z_NEAR_M = 0.05
# depth band edges [m]: a surface spanning several bands is drawn once per band
_BANDS = (Z_NEAR_M, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 1e9)


@nb.njit(cache=True, nogil=True)
def _composite(
    img: np.ndarray,
    izbuf: np.ndarray,
    warped: np.ndarray,
    mask: np.ndarray,
    x0: int,
    y0: int,
    a: float,
    b: float,
    c: float,
) -> None:  # pragma: no cover - compiled
    """Depth-tested write of one band, in one pass: where ``mask`` is set and the band's inverse
    depth 1/Z = a x + b y + c (float32, as the buffer) is nearer than ``izbuf``, write the texel and
    the depth. ``warped``/``mask`` (bh, bw) cover the image window starting at (x0, y0)."""
    bh, bw = warped.shape
    fa, fb, fc = np.float32(a), np.float32(b), np.float32(c)
    for r in range(bh):
        row = np.float32(y0 + r)
        base = fb * row + fc
        for q in range(bw):
            if mask[r, q]:
                iz = fa * np.float32(x0 + q) + base
                if iz > izbuf[y0 + r, x0 + q]:
                    izbuf[y0 + r, x0 + q] = iz
                    img[y0 + r, x0 + q] = warped[r, q]


def clip_polygon_z(poly: np.ndarray, z_lo: float, z_hi: float) -> np.ndarray:
    """Sutherland–Hodgman clip of a convex polygon (n, 3) [m] to z_lo ≤ z ≤ z_hi; returns (m, 3)."""
    for sign, bound in ((1.0, z_lo), (-1.0, z_hi)):
        if len(poly) == 0:
            return poly
        dist = sign * (poly[:, 2] - bound)
        if np.all(dist >= 0):
            continue
        out = []
        n = len(poly)
        for i in range(n):
            a, b = poly[i], poly[(i + 1) % n]
            da, db = dist[i], dist[(i + 1) % n]
            if da >= 0:
                out.append(a)
            if (da >= 0) != (db >= 0):
                out.append(a + (b - a) * (da / (da - db)))
        poly = np.array(out) if out else np.zeros((0, 3))
    return poly


def _stacked(surfaces: tuple[Surface, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corners (S, 4, 3), normals (S, 3) and origins (S, 3) of ``surfaces``, stacked for culling."""
    if not surfaces:
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return (
        np.stack([s.corners_W for s in surfaces]),
        np.stack([s.normal_W for s in surfaces]),
        np.stack([s.origin_W for s in surfaces]),
    )


class ViewRenderer:
    """Renders one pinhole view of a list of surfaces. Not thread-safe (owns scratch buffers).

    ``f_px``, ``px``, ``py`` [px]: intrinsics; ``width``×``height``: image size; ``sky`` (H, W)
    uint8: what is drawn where no surface is (infinitely far, 1/Z = 0).
    """

    def __init__(self, surfaces: tuple[Surface, ...], f_px: float, px: float, py: float, width: int, height: int):
        self.surfaces = surfaces
        self.f, self.px, self.py = float(f_px), float(px), float(py)
        self.w, self.h = int(width), int(height)
        self.K = np.array([[self.f, 0.0, self.px], [0.0, self.f, self.py], [0.0, 0.0, 1.0]])
        rows = np.linspace(235.0, 150.0, self.h, dtype=np.float32)[:, None]
        self.sky = np.broadcast_to(rows, (self.h, self.w)).astype(np.uint8)
        # stacked geometry for the vectorised cull
        self._corners, self._normals, self._origins = _stacked(surfaces)
        # frustum side-plane slopes with a one-pixel margin: |x/z| ≤ tx, |y/z| ≤ ty (roughly, per side)
        self._x_lo = (-1.0 - self.px) / self.f
        self._x_hi = (self.w - self.px) / self.f
        self._y_lo = (-1.0 - self.py) / self.f
        self._y_hi = (self.h - self.py) / self.f

    def render(self, T_world_cam: np.ndarray, moving: tuple[Surface, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
        """Render from the optical-frame pose ``T_world_cam`` (4, 4), with ``moving`` surfaces
        (already placed in the world frame for this instant) drawn as well, depth-tested with the rest.

        Returns (image (H, W) uint8, inverse depth (H, W) float32 [1/m], 0 where nothing is hit).
        """
        R_cw = T_world_cam[:3, :3].T
        t_cw = -R_cw @ T_world_cam[:3, 3]
        img = self.sky.copy()
        izbuf = np.zeros((self.h, self.w), np.float32)
        groups = [(self.surfaces, self._corners, self._normals, self._origins)]
        if moving:
            groups.append((moving, *_stacked(moving)))
        for surfaces, corners, normals, origins in groups:
            cc, inside = self._cull(corners, normals, origins, R_cw, t_cw, T_world_cam[:3, 3])
            for i in np.flatnonzero(inside):
                self._draw_surface(surfaces[i], cc[i], R_cw, t_cw, img, izbuf)
        return img, izbuf

    def _cull(
        self,
        corners: np.ndarray,
        normals: np.ndarray,
        origins: np.ndarray,
        R_cw: np.ndarray,
        t_cw: np.ndarray,
        cam_W: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised culling: back faces, fully behind the near plane, fully outside a side plane.
        Returns the corners in the camera frame (S, 4, 3) and the mask of surfaces to draw (S,)."""
        facing = np.einsum("si,si->s", normals, cam_W - origins) > 1e-9
        cc = corners @ R_cw.T + t_cw  # (S, 4, 3) camera frame
        z = cc[..., 2]
        x, y = cc[..., 0], cc[..., 1]
        inside = (
            facing
            & np.any(z > Z_NEAR_M, axis=1)
            & ~np.all(x < self._x_lo * z, axis=1)
            & ~np.all(x > self._x_hi * z, axis=1)
            & ~np.all(y < self._y_lo * z, axis=1)
            & ~np.all(y > self._y_hi * z, axis=1)
        )
        return cc, inside

    def _draw_surface(
        self, s: Surface, poly_C: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, img: np.ndarray, izbuf: np.ndarray
    ) -> None:
        n_c = R_cw @ s.normal_W
        o_c = R_cw @ s.origin_W + t_cw
        d_c = float(n_c @ o_c)  # plane n_c · X = d_c (camera frame); d_c < 0 on the visible side
        # 1/Z = (a x + b y + c) for pixel (x, y): n_c · K⁻¹ (x, y, 1) / d_c
        a = n_c[0] / (self.f * d_c)
        b = n_c[1] / (self.f * d_c)
        c = (n_c[2] - n_c[0] * self.px / self.f - n_c[1] * self.py / self.f) / d_c
        # texel (s, t, 1) → pixel, homogeneous: K [R u | R v | R o + t]
        H0 = self.K @ np.column_stack([R_cw @ s.u_W, R_cw @ s.v_W, o_c])
        zmin, zmax = float(poly_C[:, 2].min()), float(poly_C[:, 2].max())
        nlev = len(s.mips)
        for k in range(len(_BANDS) - 1):
            z_lo, z_hi = _BANDS[k], _BANDS[k + 1]
            if zmax < z_lo or zmin > z_hi:
                continue
            band = clip_polygon_z(poly_C, z_lo, z_hi)
            if len(band) < 3:
                continue
            pts = band[:, :2] / band[:, 2:3] * self.f + (self.px, self.py)
            x0 = max(0, math.floor(float(pts[:, 0].min())))
            x1 = min(self.w, math.ceil(float(pts[:, 0].max())) + 1)
            y0 = max(0, math.floor(float(pts[:, 1].min())))
            y1 = min(self.h, math.ceil(float(pts[:, 1].max())) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
            # mip level: texels per pixel at the band's near edge, with foreshortening by the
            # viewing angle (geometric mean of the two footprint axes)
            zb = max(float(band[:, 2].min()), Z_NEAR_M)
            if s.lod_nearest:
                # at the nearest corner of the band's visible window (a ground tile's band can
                # reach far to the side, out of view: neither its nearest vertex nor its centre
                # is what the image shows)
                cx = np.array([x0, x1 - 1, x0, x1 - 1], float)
                cy = np.array([y0, y0, y1 - 1, y1 - 1], float)
                iz = a * cx + b * cy + c
                j = int(np.argmax(iz))
                if iz[j] > 0.0:
                    zb = min(max(zb, 1.0 / float(iz[j])), z_hi)
                centre = np.array([(cx[j] - self.px) / self.f, (cy[j] - self.py) / self.f, 1.0])
            else:
                centre = band.mean(0)
            cos_view = abs(float(n_c @ centre)) / max(float(np.linalg.norm(centre)), 1e-9)
            ratio = zb / (self.f * s.texel_m) / math.sqrt(max(cos_view, 0.05))
            level = min(nlev - 1, max(0, math.floor(math.log2(ratio) + 0.3))) if ratio > 1.0 else 0
            scale = float(2**level)
            M = H0 @ np.diag([scale, scale, 1.0])
            M[0] -= x0 * M[2]
            M[1] -= y0 * M[2]
            bw, bh = x1 - x0, y1 - y0
            warped = cv2.warpPerspective(
                s.mips[level], M, (bw, bh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
            mask = np.zeros((bh, bw), np.uint8)
            fixed = np.round((pts - (x0, y0)) * 16.0).astype(np.int32)
            cv2.fillConvexPoly(mask, fixed, 1, cv2.LINE_8, 4)
            if s.alpha:
                cover = cv2.warpPerspective(
                    s.alpha[level], M, (bw, bh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
                )
                mask[cover < 128] = 0
            _composite(img, izbuf, warped, mask, x0, y0, a, b, c)
