"""Every numeric tolerance of the test suite, in one place, with what it bounds."""

# WoodScape model, float64, against the reference math (projection.py / np.roots), pixels.
PROJECT_PX_F64 = 1e-9
UNPROJECT_RAD_F64 = 1e-12  # ray angle vs the np.roots oracle
ROUNDTRIP_PX_F64 = 1e-9  # pixel -> ray -> pixel over the whole image
# float32 paths.
ROUNDTRIP_PX_F32 = 1e-3
# cv2.fisheye oracle (odd-only polynomial, theta < 73 deg): cv2 iterates its own undistortion.
CV2_PROJECT_PX = 1e-6
CV2_UNPROJECT_RAD = 1e-7
# Derivatives: jacfwd vs jacrev (exact), and vs central finite differences in float64.
JAC_FWD_REV = 1e-10
JAC_FINITE_DIFF_REL = 1e-5
# Rigid transforms.
POSE_F64 = 1e-12
