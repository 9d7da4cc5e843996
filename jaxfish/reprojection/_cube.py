"""The cube rig: the perspective faces a CARLA capture renders for one fisheye camera."""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import float_dtype, resolve_dtype
from ..cameras import AbstractCamera, Pinhole, WoodScapeFisheye
from ..transforms import UNREAL_CAMERA_TO_OPENCV, Pose, carla_rotation_matrix

CUBE_FACE_ROTATIONS: dict[str, tuple[float, float, float]] = {
    "front": (0.0, 0.0, 0.0),
    "left": (0.0, -90.0, 0.0),
    "right": (0.0, 90.0, 0.0),
    "top": (90.0, 0.0, 0.0),
    "bottom": (-90.0, 0.0, 0.0),
    "back": (0.0, 180.0, 0.0),
}
"""Face name -> CARLA rotation ``(pitch, yaw, roll)`` in degrees of the face camera relative to the
fisheye camera's own CARLA transform (Unreal frame). ``back`` is optional."""
FIVE_FACES: tuple[str, ...] = ("front", "left", "right", "top", "bottom")
"""The five faces SynWoodScape renders (no back face: a 190-degree lens never needs it)."""
SIX_FACES: tuple[str, ...] = FIVE_FACES + ("back",)
"""The five faces plus ``back``: a rig that sees every direction."""


def face_to_camera_rotation(face: str, *, dtype=None) -> np.ndarray:
    """Rotation taking a face camera's OpenCV frame to the fisheye camera's OpenCV frame."""
    if face not in CUBE_FACE_ROTATIONS:
        raise ValueError(f"unknown cube face {face!r}; expected one of {tuple(CUBE_FACE_ROTATIONS)}")
    pitch, yaw, roll = CUBE_FACE_ROTATIONS[face]
    r_unreal = np.asarray(carla_rotation_matrix(pitch, yaw, roll, dtype=jnp.float64 if dtype is None else dtype))
    m = UNREAL_CAMERA_TO_OPENCV
    r = m @ r_unreal.astype(np.float64) @ m.T
    return np.round(r, 12)  # exact 0/±1 entries for the axis-aligned faces


class CubeRig(AbstractCamera):
    """The 90-degree perspective faces of one fisheye camera, as CARLA captures them.

    Every face is a CARLA pinhole (fov 90, ``S x S``, ``f = S / 2``, optical axis at the
    pixel-centre coordinate ``((S-1)/2, (S-1)/2)``) attached to the fisheye camera's CARLA
    transform with the relative rotation `CUBE_FACE_ROTATIONS`. The rig's own frame is the fisheye
    camera's OpenCV frame. As a camera it maps a direction to the face whose optical axis is closest
    (the dominant-axis rule) and pixel coordinates *within that face*; `project_faces` also returns
    the face index. A direction that no face sees (behind a five-face rig) is invalid.
    """

    face: Pinhole
    face_to_camera: Pose  # batched over faces: rotation (F, 3, 3), translation (F, 3) = 0
    faces: tuple[str, ...] = eqx.field(static=True)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, face_size: int, *, faces: tuple[str, ...] = FIVE_FACES, dtype=None):
        dtype = resolve_dtype(dtype)
        face_size = int(face_size)
        if face_size <= 0:
            raise ValueError(f"CubeRig: face_size must be positive, got {face_size}")
        faces = tuple(faces)
        if len(set(faces)) != len(faces) or not faces:
            raise ValueError(f"CubeRig: faces must be distinct and non-empty, got {faces}")
        rots = np.stack([face_to_camera_rotation(f) for f in faces])
        self.face = Pinhole.from_fov(face_size, face_size, 90.0, dtype=dtype)
        self.face_to_camera = Pose(rots, np.zeros((len(faces), 3)), dtype=dtype)
        self.faces = faces
        self.width = face_size
        self.height = face_size

    @property
    def face_size(self) -> int:
        """Side ``S`` of every square face, in pixels."""
        return self.width

    def face_index(self, name: str) -> int:
        """Index of a face name in `faces`."""
        return self.faces.index(name)

    def face_pose(self, name: str) -> Pose:
        """face OpenCV frame -> fisheye camera OpenCV frame."""
        i = self.face_index(name)
        return Pose(self.face_to_camera.rotation_matrix[i], self.face_to_camera.translation[i])

    def project_faces(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Int[Array, "*batch"], Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """``(face index, pixel in that face, valid)`` of rig-frame points (dominant-axis rule)."""
        p = jnp.asarray(points)
        if p.shape[-1:] != (3,):
            raise ValueError(f"CubeRig.project_faces: points must have shape (..., 3), got {p.shape}")
        dtype = float_dtype(p)
        p = p.astype(dtype)
        finite = jnp.all(jnp.isfinite(p), axis=-1)  # a non-finite point would put NaN into the rotations' gradient
        p = jnp.where(finite[..., None], p, jnp.zeros_like(p))
        rots = self.face_to_camera.rotation_matrix.astype(dtype)  # (F, 3, 3)
        axes = rots[:, :, 2]  # each face's optical axis in the rig frame, (F, 3)
        # Multiply-adds on coordinate planes rather than dots over a minor axis of 3, which
        # XLA:CPU hands to a library kernel several times slower.
        x, y, z = (p[..., k, None] for k in range(3))
        along = x * axes[:, 0] + y * axes[:, 1] + z * axes[:, 2]
        idx = jnp.argmax(along, axis=-1)
        r_sel = rots[idx]  # (..., 3, 3)
        local = x * r_sel[..., 0, :] + y * r_sel[..., 1, :] + z * r_sel[..., 2, :]  # R^T p
        uv, valid = self.face.project(local)
        valid = finite & valid & self.face.contains(uv)
        return idx, uv, valid

    def project(
        self, points: Float[ArrayLike, "*batch 3"]
    ) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
        """Pixel within the dominant face (see `project_faces` for the face index)."""
        _, uv, valid = self.project_faces(points)
        return uv, valid

    def unproject_faces(
        self, face_index: Int[ArrayLike, "*batch"], uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Rig-frame unit rays of face pixels (face given by index)."""
        uv = jnp.asarray(uv)
        dtype = float_dtype(uv)
        local, valid = self.face.unproject(uv.astype(dtype))
        rots = self.face_to_camera.rotation_matrix.astype(dtype)[jnp.asarray(face_index)]
        return jnp.einsum("...jk,...k->...j", rots, local), valid

    def unproject(
        self, uv: Float[ArrayLike, "*batch 2"]
    ) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
        """Rays of pixels of the *first* face (use `unproject_faces` to name the face)."""
        uv = jnp.asarray(uv)
        return self.unproject_faces(jnp.zeros(uv.shape[:-1], jnp.int32), uv)


def cube_face_size(camera: WoodScapeFisheye, *, multiple: int = 32, oversample: float = 1.0) -> int:
    """Smallest face size ``S`` (a multiple of `multiple`) whose faces never undersample the fisheye.

    A 90-degree face has focal ``S/2`` pixels per radian at its centre, its lowest angular density;
    the fisheye's densest direction inside its image is ``max(d rho/d theta, rho / sin theta)``
    (radial and tangential pixels per radian) over the image's incidence angles. So
    ``S >= 2 * oversample * max_density`` (CONVENTIONS §7).
    """
    cam = camera
    h, w = camera.height, camera.width
    k = np.asarray(cam.k, dtype=np.float64)
    # Incidence angles reached inside the image: the corners bound them. Plain float64 NumPy (a
    # monotone bisection on rho), so this host-side helper costs no JAX tracing or compilation.
    cx = w / 2 + float(cam.cx_offset) - 0.5
    cy = h / 2 + float(cam.cy_offset) - 0.5
    a_r = float(cam.aspect_ratio)
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    rho_img = float(np.max(np.hypot(corners[:, 0] - cx, (corners[:, 1] - cy) / a_r)))
    grid = np.linspace(0.0, math.pi, 4097)
    drho_grid = k[0] + grid * (2 * k[1] + grid * (3 * k[2] + grid * 4 * k[3]))
    stationary = np.nonzero(drho_grid <= 0)[0]
    theta_hi = grid[stationary[0]] if stationary.size else math.pi
    lo, hi = 0.0, theta_hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        rho_mid = mid * (k[0] + mid * (k[1] + mid * (k[2] + mid * k[3])))
        lo, hi = (mid, hi) if rho_mid < rho_img else (lo, mid)
    theta_img = hi
    thetas = np.linspace(1e-3, theta_img, 2048)
    drho = k[0] + thetas * (2 * k[1] + thetas * (3 * k[2] + thetas * 4 * k[3]))
    rho = thetas * (k[0] + thetas * (k[1] + thetas * (k[2] + thetas * k[3])))
    a = float(np.max(np.asarray(cam.aspect_ratio)))
    density = np.maximum(drho, rho / np.sin(thetas)) * max(a, 1.0)
    s = 2.0 * oversample * float(np.max(density))
    return int(math.ceil(s / multiple) * multiple)


class UndersampledFacesWarning(UserWarning):
    """Cube faces too small for a target camera: their focal ``S/2`` is below the target's largest
    radial density (`max_radial_density`), so the resampled image is blocky (CONVENTIONS §7)."""


def max_radial_density(camera: AbstractCamera, *, num_theta: int = 1024, num_phi: int = 256) -> float:
    """The camera's largest ``d rho / d theta`` in pixels per radian over its image.

    Rays on a grid of incidence angles ``theta`` (from the optical axis, ``+z``) and azimuths are
    projected; the derivative ``|d uv / d theta|`` is exact (forward-mode autodiff of `project`)
    and taken where the ray lands inside the image, along each azimuth up to the first ray that is
    invalid or whose pixel stops moving away from the optical axis's. Works for every camera model;
    non-radial models (``fx != fy``, aspect ratios) are covered by the azimuth grid. 0 when no
    sampled ray lands in the image. Host-side: call it with concrete cameras, not under `jax.jit`.
    """
    import jax

    cam = camera
    floats = [x for x in jax.tree_util.tree_leaves(cam) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating)]
    dtype = floats[0].dtype if floats else jnp.float32
    theta = jnp.linspace(1e-3, math.pi - 1e-3, num_theta, dtype=dtype)[:, None]
    phi = jnp.linspace(0.0, 2 * math.pi, num_phi, endpoint=False, dtype=dtype)[None, :]

    def project(t):
        st = jnp.sin(t)
        rays = jnp.stack(jnp.broadcast_arrays(st * jnp.cos(phi), st * jnp.sin(phi), jnp.cos(t)), axis=-1)
        return cam.project(rays)

    (uv, valid), (duv, _) = jax.jvp(project, (theta,), (jnp.ones_like(theta),))
    density = jnp.linalg.norm(duv, axis=-1)
    centre, _ = cam.project(jnp.asarray([0.0, 0.0, 1.0], dtype))
    # Only the rays that are their pixels' rays: along each azimuth, up to the first ray that is
    # invalid or no longer moves away from the image of the axis (a model whose projection folds
    # back, e.g. a converted double sphere near 180 degrees, reuses those pixels for other rays).
    outward = jnp.sum(duv * (uv - centre), axis=-1) > 0
    ok = valid & outward & jnp.all(jnp.isfinite(uv), axis=-1) & jnp.isfinite(density)
    ok = jnp.cumprod(ok, axis=0).astype(bool) & cam.contains(uv)
    return float(jnp.max(jnp.where(ok, density, 0.0)))


def warn_undersampled_faces(face_size: int, cameras: AbstractCamera | dict[str, AbstractCamera], *,
                            stacklevel: int = 2) -> str | None:
    """Warn (one `UndersampledFacesWarning`) when ``face_size``-pixel cube faces undersample a camera.

    A 90-degree face of ``S`` pixels has focal ``S/2`` pixels per radian, its lowest angular
    density; the target needs ``S/2 >= max_radial_density(camera)`` (CONVENTIONS §7). ``cameras``
    is one camera or ``{name: camera}``; one warning names the worst camera and the smallest
    sufficient face size. Returns the warning's message, or None when the faces suffice.
    `cube_face_size` gives the larger size that also matches the tangential density of a
    `WoodScapeFisheye`.
    """
    named = cameras if isinstance(cameras, dict) else {"": cameras}
    worst_name, worst = None, 0.0
    for name, cam in named.items():
        density = max_radial_density(cam)
        if density > worst:
            worst_name, worst = name, density
    focal = int(face_size) / 2.0
    if worst_name is None or focal >= worst:
        return None
    cam = named[worst_name]
    label = f"the {worst_name} camera" if worst_name else "the target camera"
    minimum = int(math.ceil(2.0 * worst))
    message = (f"cube faces of {int(face_size)} px undersample {label} ({cam.width}x{cam.height}): their focal "
               f"length {focal:g} px/rad is below its largest radial density {worst:.1f} px/rad, so the result "
               f"is blocky; use a cube_face_size of at least {minimum} px")
    if isinstance(cam, WoodScapeFisheye):
        message += f" (jaxfish.cube_face_size(camera) = {cube_face_size(cam)} also matches its tangential density)"
    warnings.warn(message, UndersampledFacesWarning, stacklevel=stacklevel)
    return message
