"""The dataset builder (edge, may import `jaxfish.io`): frames from a source (a capture directory,
the embedded scene in memory) through `jaxfish.pipeline.sample_truth` into the SynWoodScape layout
(`LayoutSink`), resumable and scalable on dask.distributed (see ``docs/dataset.md``)."""

from ._build import DONE_DIR as DONE_DIR
from ._build import BuildInterrupted as BuildInterrupted
from ._build import BuildOptions as BuildOptions
from ._build import BuildReport as BuildReport
from ._build import DatasetError as DatasetError
from ._build import build_dataset as build_dataset
from ._build import build_sample as build_sample
from ._build import build_samples as build_samples
from ._build import capture_fingerprint as capture_fingerprint
from ._build import check_output_folder as check_output_folder
from ._build import clear_worker_cache as clear_worker_cache
from ._build import frame_fingerprint as frame_fingerprint
from ._build import has_bev as has_bev
from ._build import is_complete as is_complete
from ._build import local_cluster as local_cluster
from ._build import remove_sample_files as remove_sample_files
from ._build import remove_stale_temporaries as remove_stale_temporaries
from ._build import rig_constants_of as rig_constants_of
from ._contact import CONTACT_COLUMNS as CONTACT_COLUMNS
from ._contact import CONTACT_ROWS as CONTACT_ROWS
from ._contact import contact_sheet as contact_sheet
from ._contact import write_contact_sheet as write_contact_sheet
from ._layout import BEV_CAMERA as BEV_CAMERA
from ._layout import DATASET_FILES as DATASET_FILES
from ._layout import FISHEYE_CAMERAS as FISHEYE_CAMERAS
from ._layout import LAYOUT as LAYOUT
from ._layout import LAYOUT_VERSION as LAYOUT_VERSION
from ._layout import SAMPLE_DIGITS as SAMPLE_DIGITS
from ._layout import layout_entries as layout_entries
from ._layout import sample_files as sample_files
from ._layout import sample_id as sample_id
from ._manifest import DATASET_FORMAT as DATASET_FORMAT
from ._manifest import dataset_manifest as dataset_manifest
from ._manifest import write_dataset_files as write_dataset_files
from ._runtime import core_shares as core_shares
from ._runtime import share_cores as share_cores
from ._runtime import tune_allocator as tune_allocator
from ._sink import LayoutSink as LayoutSink
from ._sink import synwoodscape_palette_dict as synwoodscape_palette_dict
from ._sources import CaptureSource as CaptureSource
from ._sources import EmbeddedSource as EmbeddedSource
from ._sources import FrameSource as FrameSource
from ._sources import as_source as as_source
