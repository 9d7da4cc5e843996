"""One small capture (the demo's settings at scale 0.05: fisheyes 64 x 48, BEV 51 px, 2 frames) and
one serial reference build of it, shared by every dataset test."""

from __future__ import annotations

import pytest

from jaxfish.dataset import build_dataset

from .small_capture import small_capture_dir


@pytest.fixture(scope="session")
def small_capture():
    return small_capture_dir()


@pytest.fixture(scope="session")
def reference_build(small_capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("dataset_reference") / "dataset"
    report = build_dataset(small_capture, out)
    assert report.ok, report.summary()
    return out, report
