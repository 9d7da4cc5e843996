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
# Reprojection (LUTs and resampling kernels).
LUT_PX_F64 = 1e-8  # float64 LUT coordinates vs the geometry typed in independently
CV2_REMAP_F32 = 2e-6  # bilinear vs cv2.remap on float32 images in [0, 1], maps on the 1/32-px grid
ANALYTIC_CUBE = 3e-3  # cube -> fisheye of a smooth function of the ray (64-px faces, incl. seams and corners)
DEPTH_PLANE_REL_F32 = 2e-6  # range of a plane through the depth kernel (float32 faces)
DEPTH_SPHERE_REL_F32 = 2e-4  # range of a sphere (inverse depth is not affine on it: 2nd order)
# Embedded scene (float32 ray caster).
SCENE_CLOSED_FORM_M = 1e-5  # ray/box, capsule, plane distances vs closed forms (float32, ~10 m)
SCENE_PLANAR_DEPTH_REL = 1e-5  # planar depth = range * cos(angle to the axis)
SCENE_ROAD_Z_M = 5e-3  # road pixels unprojected from encoded depth land on z = 0 (float32, 24-bit depth)
SCENE_BOX_PAD_M = 5e-3  # actor pixels unprojected from depth lie inside the actor's box (+ this)
CARLA_DEPTH_QUANTUM_M = 1000.0 / (256**3 - 1)  # one step of CARLA's 24-bit depth encoding
# Oracle (cube -> fisheye pipeline vs direct fisheye rendering, small rig, 64-px faces).
ORACLE_DEPTH_REL_MEDIAN = 0.01
ORACLE_LABEL_AGREEMENT = 0.93
ORACLE_RGB_PSNR_DB = 20.0
# Lens models (Kannala-Brandt, UCM, EUCM, double sphere), float64.
MODEL_PX_F64 = 1e-9  # projection vs an independent closed form / round trips, pixels
MODEL_RAY_F64 = 1e-12  # unit-ray components after a round trip
MODEL_PX_F32 = 2e-3  # float32 pixel -> ray -> pixel
EAGER_JIT_PX_F32 = 1e-5  # one float32 projection eager vs jit / vmap (XLA may fuse into FMAs: ulps)
EAGER_JIT_REL_F32 = 1e-6  # the same, relative: pixels of huge (~1e24) points differ by float32 ulps (~1e-7)
# Refitting and model conversion.
CONVERT_EXACT_PX = 1e-7  # conversions that have an exact solution (WoodScape k2 = k4 = 0 <-> KB)
REFIT_SIGMA_BOUND = 4.0  # recovered parameters within this many estimated standard deviations
REFIT_RMS_NOISE_REL = 0.1  # fitted RMS within 10 % of the injected noise RMS
REFIT_NOISELESS_PX = 1e-6  # noiseless synthetic correspondences are fitted exactly
# Ground truth (jaxfish.groundtruth).
FLOW_CLOSED_FORM_PX_F64 = 1e-9  # analytic flow vs closed forms (pinhole translation, top view), float64
FLOW_ORACLE_EPE_PX = 1e-2  # analytic flow from the oracle's own range and actors vs its per-pixel motion (float32)
FLOW_PIPELINE_EPE_MEDIAN_PX = 0.1  # cube faces -> fisheye -> flow vs the oracle motion, median end-point error
FLOW_PIPELINE_EPE_P90_PX = 0.5  # ... 90th percentile (depth edges resampled from another surface dominate the tail)
FLOW_WARP_RGB_MEAN = 0.03  # mean |I_t(p + flow) - I_{t-1}(p)| on valid pixels, RGB in [0, 1] (bilinear texture sampling)
ATAN_F32_ULP = 3.0  # float32 polynomial arctan (Cephes atanf) vs float64 arctan: ulp of the result
FLOW_COLOR_JPEG = 6.0  # flow colour coding vs flow_vis' JPEG reference: mean absolute difference (uint8 levels)
INSTANCE_ORACLE_AGREEMENT = 0.98  # fraction of the oracle's actor pixels given the same actor id
KITTI_FLOW_PX = 1.0 / 128  # KITTI PNG quantisation (1/64 px steps)
# Bird's-eye view (jaxfish.bev).
BEV_HEIGHT_FROM_DEPTH_M = 2e-3  # height from the 24-bit BEV depth (50 m camera, float32) vs the capture's EXR
BEV_FUSED_HEIGHT_M = 1e-3  # fused height of a box top vs its known height (1 mm z-buffer quantum, float32 points)
# CARLA capture: height map from a view's 24-bit planar depth vs the embedded scene's exact world z.
CARLA_HEIGHT_FROM_DEPTH_M = 2e-3
BEV_EAGER_JIT_CELL_FRACTION = 2e-3  # fused cells that may differ between eager / jit / vmap (float32 rounding at cell edges)
BEV_GRID_M = 1e-4  # BEV pixel <-> vehicle ground point vs the documented formula (float32, 10 m)
BEV_FLOW_UNIFORM_PX = 1e-3  # top-view flow under pure ego translation vs the uniform closed form (float32)
# Batched rig ground truth: float32 flow of differently fused programs (pose products at up to 1000 m).
RIG_FLOW_PX_F32 = 5e-3
RIG_RANGE_REL_F32 = 1e-5
# Overlays (jaxfish show): box edges and lidar points drawn into fisheye images.
OVERLAY_SAMPLE_RAY_RAD = 1e-9  # float64 edge samples: unprojected pixel ray vs the sample's direction
OVERLAY_DRAWN_PX = 1.0  # every drawn wireframe pixel: the nearest box edge point projects within this
# Flow masks (valid / occluded) of the cube -> fisheye pipeline vs the embedded scene's exact ray cast at t.
FLOW_MASK_ORACLE_REL = 1e-3  # the oracle's "seen": nothing hit nearer than the moved point by this relative margin
FLOW_MASK_ORACLE_AGREEMENT = 0.98  # fraction of pixels whose mask equals the oracle's (resampled edges differ)
FLOW_OCCLUSION_ORACLE_RECALL = 0.85  # oracle-hidden pixels the pipeline flags occluded
FLOW_OCCLUSION_ORACLE_PRECISION = 0.9  # pipeline-occluded pixels the oracle finds hidden
# Sensors in the vehicle frame (dataset sensor_data, lidar_vehicle).
SENSOR_FRAME_F64 = 1e-9  # conversions and round trips in float64 (metres, rad/s)
LIDAR_FLOAT32_M = 1e-4  # float32 lidar points mapped back to the raw sensor frame (metres, within 100 m)
LIDAR_ON_DEPTH_REL = 0.02  # lidar range seen from a fisheye vs the 4 depth-map pixels around its projection
LIDAR_ON_DEPTH_BRACKETED = 0.7  # fraction within [min, max] of those 4 ranges (+- LIDAR_ON_DEPTH_REL); the rest are
# hidden from the camera (behind the ego body, a mirror or a nearer object: the lidar sits on the roof)
LIDAR_IN_FRONT_OF_DEPTH = 0.03  # fraction nearer than every one of the 4 (a point in front of the visible surface)
