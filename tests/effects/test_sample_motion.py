"""sample_motion: a moving part of the sample is one region of pixels whose frames disagree."""
import numpy as np

from dfxcorr.effects.sample_motion import MIN_GROUPED, REACH, grouped


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
