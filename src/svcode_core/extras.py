"""Optional dependencies, each installed by an extra of napari-svcode and imported only by
what needs it: ``dask`` (``distributed``: frames on a dask cluster). The benchmark engine,
``svcode_bench``, comes with a source checkout (its ``bench`` folder) and the ``bench``
extra.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["NotInstalled", "require"]


class NotInstalled(ImportError):
    """An optional part is not installed; the message says in one line how to install it
    (the ``svcode`` command reports it as a user error, exit status 2)."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module``, an optional dependency that the extra ``extra`` installs.

    Raises
    ------
    NotInstalled
        If ``module`` is not installed, naming ``purpose`` and the extra.

    Examples
    --------
    >>> require("json", "none", "reading JSON").__name__
    'json'
    >>> require("no_such_module", "dask", "frames on a dask cluster")
    Traceback (most recent call last):
    ...
    svcode_core.extras.NotInstalled: frames on a dask cluster: no_such_module is not installed; pip install "napari-svcode[dask]"
    """  # noqa: E501
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name is None or not (module + ".").startswith(err.name + "."):
            raise  # the module is there but something it imports is not: a real error
        raise NotInstalled(
            f'{purpose}: {module} is not installed; pip install "napari-svcode[{extra}]"'
        ) from err
