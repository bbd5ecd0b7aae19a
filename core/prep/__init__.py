"""Raw scan preparation (``bubsub prepare``): readers, flat/dark correction, bad pixels, phase retrieval,
stripes, rotation centre, background and contrast, streamed in slabs to a scan file."""

from bubsub.core.prep.options import PrepareOptions, prepare_options
from bubsub.core.prep.pipeline import prepare
from bubsub.core.prep.readers import RawSource, open_raw

__all__ = ["prepare", "prepare_options", "PrepareOptions", "open_raw", "RawSource"]
