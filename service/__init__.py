"""The REST service: a thin shell around :mod:`recovery`."""

import warnings as _warnings

# colour-science warns on import when Matplotlib is missing ("Matplotlib"
# related API features are not available), which this service never uses
# (Matplotlib is only in the bench extra): every command and the server log
# printed it. Filtered here, before anything imports colour; only that one
# message from colour's own modules, every other warning is kept.
_warnings.filterwarnings("ignore", message='"Matplotlib" related API features are not available',
                         module=r"colour(\.|$)")
