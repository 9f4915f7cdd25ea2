"""Motion-pixel masking (paper Sec. II-E) on a region that moves during the scan."""
import numpy as np

from dfxcorr import config as C
from dfxcorr import pipeline
from dfxcorr.align import build_observations
from dfxcorr.mask import motion_mask
from dfxcorr.reference import resolve_reference


def test_moving_region_is_flagged_and_little_else(small_scan):
    scan, truth = small_scan(**{"effects.sample_motion": 0.3})
    obs = build_observations(scan, resolve_reference(scan))
    moving, score, thr = motion_mask(obs, dilate=0)
    region = truth["motion_mask"]
    lit_region = region & (truth["image_transmission"] > 0.01)
    assert moving[lit_region].mean() > 0.8
    assert moving[~region].mean() < 0.01


def test_clean_scan_masks_almost_nothing(small_scan):
    scan, _ = small_scan()
    moving, _, _ = motion_mask(build_observations(scan, resolve_reference(scan)), dilate=0)
    assert moving.mean() < 0.01
    moving, _, _ = motion_mask(build_observations(scan, resolve_reference(scan)), dilate=1)
    assert moving.mean() < 0.05  # the dilation grows each isolated false alarm to up to 5 pixels


def test_mask_keeps_moving_pixels_out_of_the_fit_only(small_scan):
    scan, truth = small_scan(**{"effects.sample_motion": 0.3})
    result = pipeline.reconstruct(scan, C.load([], ["fit.subsample=3"]))
    region = truth["motion_mask"]
    assert result.fit_mask[region].sum() == 0
    assert np.isfinite(result.transmission[region]).mean() > 0.9  # retrieved all the same
    assert result.motion_mask[region].mean() > 0.8
