"""trimeter.fit's loading (trimeter.inversion.artifacts): what is no map is refused by name."""

import pytest

from trimeter.errors import InputError
from trimeter.inversion.artifacts import ArtifactCache, fit


def test_fit_refuses_what_is_no_map():
    with pytest.raises(InputError, match="is no map"):
        fit(42, [0.1], [0.3], [0.5], cache=ArtifactCache())  # type: ignore[arg-type]


def test_several_maps_go_in_a_list_or_a_tuple():
    with pytest.raises(InputError, match="list or a tuple, not a range"):
        fit(range(2), [0.1], [0.3], [0.5], cache=ArtifactCache())  # type: ignore[arg-type]
