"""The renderer in a child process: the same images as in-process, errors carried back, no orphan child."""
from __future__ import annotations

import copy
import os

import numpy as np
import pytest

from drivers.loopback.render_process import RenderProcess, RenderProcessError
from drivers.loopback.xray_render import (
    BiplaneRenderer,
    RobotBody,
    RobotPose,
    VesselPhantom,
    biplane_views,
)

SMALL = {"fov_mm": (150.0 * 191 / 768, 130.0 * 167 / 672), "image_size": (191, 167)}
BODY = RobotBody(length_mm=10.0, diameter_mm=2.0, tip_angle_deg=20.0, attenuation_per_mm=1.0)


def make_renderer() -> BiplaneRenderer:
    vessel = VesselPhantom(np.array([[-30.0, 0.0, 0.0], [30.0, 5.0, 0.0]]), 2.5, 0.05)
    return BiplaneRenderer(biplane_views(**SMALL), BODY, vessel=vessel, seed=3)


def poses() -> list[RobotPose | None]:
    return [RobotPose(np.array([1.0, 2.0, 0.5]), np.array([1.0, 0.2, 0.1])), None,
            RobotPose(np.array([-4.0, 1.0, 0.0]), np.array([0.3, -1.0, 0.2]))]


def test_child_renders_the_same_images_and_truth_in_the_same_order() -> None:
    local = make_renderer()
    remote_source = copy.deepcopy(local)
    with RenderProcess(remote_source) as remote:
        assert remote.process is not None and remote.process.pid != os.getpid()
        for pose in poses():
            mine, theirs = local.render(pose), remote.render(pose)
            assert sorted(theirs.images) == ["p", "q"]
            for plane in ("p", "q"):
                assert theirs.images[plane].dtype == np.uint16
                np.testing.assert_array_equal(theirs.images[plane], mine.images[plane])   # noise included
            assert sorted(theirs.truth) == sorted(mine.truth)
            for plane in mine.truth:
                assert theirs.truth[plane].pixel_count == mine.truth[plane].pixel_count
            assert (theirs.head_mm is None) == (mine.head_mm is None)
        first = remote.render(poses()[0]).images["p"]
        second = remote.render(poses()[0]).images["p"]
        assert first is not second and not np.shares_memory(first, second)   # the caller owns its arrays
        assert remote.settings == local.settings and remote.views.keys() == local.views.keys()


def test_an_error_in_the_child_is_raised_in_the_parent_and_the_child_goes_on() -> None:
    phantom_only = BiplaneRenderer(biplane_views(**SMALL), None, seed=0)
    with RenderProcess(phantom_only) as remote:
        with pytest.raises(RenderProcessError, match="no robot body"):
            remote.render(poses()[0])
        assert remote.render(None).images["q"].shape == (167, 191)


def test_close_ends_the_child_and_removes_the_frames_file() -> None:
    remote = RenderProcess(make_renderer())
    assert remote.process is not None
    assert os.path.exists(remote.shm_path)
    remote.close()
    remote.close()                                    # idempotent
    assert remote.process.poll() is not None
    assert not os.path.exists(remote.shm_path)
    with pytest.raises(RenderProcessError, match="closed"):
        remote.render(None)


@pytest.mark.parametrize("how", ["sigint", "sigkill"])
def test_the_child_does_not_outlive_its_parent(child_outlives_no_parent, how: str) -> None:
    """Ctrl-C (SIGINT to the process group) or a killed parent: the render child ends with it."""
    child_outlives_no_parent("""
        from drivers.loopback.render_process import RenderProcess
        from drivers.loopback.xray_render import BiplaneRenderer, biplane_views
        device = RenderProcess(BiplaneRenderer(biplane_views(fov_mm=(40.0, 35.0), image_size=(64, 56)), None))
        device.render(None)
    """, how, "render")
