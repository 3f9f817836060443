"""Material-distribution metrics (M3ashy §4.2): pairwise distances between two sets of
materials (`distances`), the set metrics MMD / COV / 1-NNA built on them (`sets`), FID on
renders with an Inception-v3 (`fid`, `inception`), and the whole Table-2 evaluation (`evaluate`)."""

from neumat.logs import InputError


class MetricsInputError(InputError, ValueError):
    """Input the metrics cannot score (non-finite samples, a reference prepared for other
    settings, a table row short of draws): the message names the file or model and what to do."""
