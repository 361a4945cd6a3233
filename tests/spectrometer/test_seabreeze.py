"""The seabreeze backend is optional: without python-seabreeze it says how to get it."""

import importlib.util

import pytest

from trimeter.errors import DeviceError
from trimeter.spectrometer import open_spectrometer


@pytest.mark.skipif(importlib.util.find_spec("seabreeze") is not None, reason="python-seabreeze is installed")
def test_missing_seabreeze_is_a_clear_error():
    with pytest.raises(DeviceError, match=r"pip install 'trimeter\[seabreeze\]'"):
        open_spectrometer("seabreeze:")
