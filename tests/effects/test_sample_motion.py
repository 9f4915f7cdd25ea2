"""sample_motion: a moving part of the sample is one region of pixels whose frames disagree."""
import numpy as np

from dfxcorr.effects import base
from dfxcorr.effects.sample_motion import EFFECT, MIN_GROUPED, REACH, grouped


def test_one_region_is_grouped_and_scattered_clusters_are_not():
    r, c = np.mgrid[:60, :80]
    disc = (r - 30) ** 2 + (c - 40) ** 2 < 8 ** 2
    assert grouped(disc) == 1.0
    # its rim broken into arcs a pixel apart is still one region
    rim = disc & ((r - 30) ** 2 + (c - 40) ** 2 >= 6 ** 2) & (c % 3 != 0)
    assert grouped(rim) == 1.0
    # short edges spread over the detector (what images on the pixel grid leave of a parallax): none holds many
    edges = np.zeros_like(disc)
    for k in range(10):
        edges[5 + 5 * k, 4 + 7 * k:8 + 7 * k] = True
    assert grouped(edges) == 0.1 < MIN_GROUPED
    # clusters REACH pixels from meeting each other's grown edge join; one pixel further they do not
    for gap, share in ((2 * REACH, 1.0), (2 * REACH + 1, 0.5)):
        two = np.zeros_like(disc)
        two[10, 10:13] = two[10, 13 + gap:16 + gap] = True
        assert grouped(two) == share
    assert grouped(np.zeros_like(disc)) == 1.0


def test_the_unexplained_entry_says_why_the_pixels_are_no_moving_part():
    """Pixels a moving part could be but whose masking explained nothing, and pixels that are none (the reasons
    the test gave, each named)."""
    flag = np.zeros((20, 30), bool)
    flag[2, 3:6] = flag[12, 20:23] = True
    for reasons, said in (((), "6 pixels whose frames disagree beyond noise, in clusters; masking them does not "),
                          (("more than 10 % of the pixels",), "; more than 10 % of the pixels: no moving part"),
                          (("too many", "scattered"), "; too many; scattered: no moving part of a sample")):
        u = EFFECT.unexplained(base.Test(50.0, 6, 1e-9, np.log(1e-9), reasons, material=not reasons, flagged=flag))
        assert u.axis == "pixel" and said in u.description, u.description
        assert u.where == "6 pixels in rows 2-12, columns 3-22"
