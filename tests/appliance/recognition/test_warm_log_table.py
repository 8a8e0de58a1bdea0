"""The steady path's log-table warming reads one entry per cache line over exactly the ROI's gray levels."""
import numpy as np

from appliance.recognition import steady_kernels


def test_reads_one_entry_per_line_from_the_rois_lowest_to_its_highest_level():
    table = np.arange(65536, dtype=np.float32)          # entry i holds i: the sum names the entries read
    image = np.full((20, 30), 5000, dtype=np.uint16)    # outside the ROI: must not widen the range
    image[4:9, 6:16] = 1000
    image[5, 7] = 1003                                  # the ROI's lowest level is 1000, its highest 1200, a line's first entry
    image[8, 15] = 1200
    got = steady_kernels._warm_log_table(image, 4, 9, 6, 16, table)
    lines = range(992, 1216, 16)                        # every line holding a level in 1000..1200
    assert got == float(sum(lines))
    assert 1200 in lines and 992 in lines


def test_stops_at_the_tables_end():
    table = np.ones(65536, dtype=np.float32)
    image = np.full((4, 4), 65535, dtype=np.uint16)
    assert steady_kernels._warm_log_table(image, 0, 4, 0, 4, table) == 1.0   # only the last line's first entry
