"""One small capture (the demo's settings at scale 0.05: fisheyes 64 x 48, BEV 51 px, 2 frames) and
one serial reference build of it, shared by every dataset test."""

from __future__ import annotations

import pytest

from jaxfish.cli._demo import demo_config, demo_rig
from jaxfish.dataset import build_dataset
from jaxfish.io import synthesize_capture

SCALE = 0.05


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset_capture") / "capture"
    synthesize_capture(root, demo_rig(SCALE), frames=2, seed=1, config=demo_config(SCALE))
    return root


@pytest.fixture(scope="session")
def reference_build(small_capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("dataset_reference") / "dataset"
    report = build_dataset(small_capture, out)
    assert report.ok, report.summary()
    return out, report
