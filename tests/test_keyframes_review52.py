"""Review 52, F6: KeyframeIndex checks its sizes on entry. A cell size of 0 or NaN was
accepted: every block fell in one cell of NaN (numpy's divide warnings at each eviction) and
eviction went oldest first whatever the coverage."""

import numpy as np
import pytest

from fusedmosaic.estimation.keyframes import KeyframeIndex

CELL = ("KeyframeIndex: cell_size_px (the crowding grid's cell, reference pixels) must be a "
        "finite number > 0, got ")


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"cell_size_px": 0.0}, CELL + "0.0"),
    ({"cell_size_px": float("nan")}, CELL + "nan"),
    ({"cell_size_px": -200.0}, CELL + "-200.0"),
    ({"cell_size_px": float("inf")}, CELL + "inf"),
    ({"cell_size_px": "200"}, CELL + "'200'"),
    ({"cell_size_px": True}, CELL + "True"),
    ({"block_size": 0}, "KeyframeIndex: block_size must be an integer >= 1, got 0"),
    ({"block_size": float("nan")}, "KeyframeIndex: block_size must be an integer >= 1, got nan"),
    ({"block_size": 2.5}, "KeyframeIndex: block_size must be an integer >= 1, got 2.5"),
    ({"max_blocks": 0}, "KeyframeIndex: max_blocks must be an integer >= 1, got 0"),
    ({"max_blocks": float("nan")}, "KeyframeIndex: max_blocks must be an integer >= 1, got nan"),
])
def test_bad_sizes_are_refused(kwargs, message):
    args = {"block_size": 2, **kwargs}
    with pytest.raises(ValueError) as info:
        KeyframeIndex(args.pop("block_size"), **args)
    assert str(info.value) == message


def test_valid_sizes_evict_from_the_most_crowded_cell():
    """numpy scalars are sizes too; eviction still takes the oldest block of the most crowded
    cell (the sequential mosaicker passes 0.5 * max(frame size), a float)."""
    index = KeyframeIndex(np.int64(1), max_blocks=np.int64(3), cell_size_px=np.float32(100.0))
    assert index.add(0, np.array([10.0, 10.0])) == []
    assert index.add(1, np.array([500.0, 10.0])) == []
    assert index.add(2, np.array([520.0, 30.0])) == []
    # a fourth block: frames 1 and 2 share a cell, the most crowded: its oldest, 1, goes
    assert index.add(3, np.array([900.0, 10.0])) == [1]
    assert sorted(index.centroids()[0].tolist()) == [0, 2, 3]
