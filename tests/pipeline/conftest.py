"""The small capture and its reference build, shared with tests/dataset."""

from tests.dataset.conftest import reference_build as reference_build  # noqa: F401
from tests.dataset.conftest import small_capture as small_capture  # noqa: F401
