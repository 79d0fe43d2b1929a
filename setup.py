"""The dependencies of the ``tactiled`` distribution; every other setting is in pyproject.toml.

They are computed here because of one of them: ``tactiled-client``, the client library (clients/), is its own
distribution and the only owner of ``tactiled_client``, which tactiled imports (schema, endpoints). A requirement
cannot name a path relative to the project (PEP 508 wants a URL), so when clients/ is beside this file (a checkout,
or a git clone pip made) the requirement is ``tactiled-client @ file:///<absolute path of clients>``, and
``pip install .`` installs both from the checkout with no package index serving the client. Without clients/ (an
sdist's own build) it is ``tactiled-client==<this version>``, for a package index.

setuptools puts into the wheel whatever build/lib holds, stale files too (pypa/setuptools#1871), and builds of this
checkout from before the split left tactiled_client there: that folder is removed before the build.
"""

from __future__ import annotations

import shutil
import tomllib
from pathlib import Path

from setuptools import setup

HERE = Path(__file__).resolve().parent
CLIENTS = HERE / "clients"

THIRD_PARTY = [
    "pyserial>=3.5",
    "numpy>=1.26",
    "scipy>=1.11",
    "PyWavelets>=1.5",
    "scikit-learn>=1.4",
    "pyzmq>=25",
    "msgpack>=1.0",
    "minisom>=2.3",
    "threadpoolctl>=3.1",
    "rich>=13",
]


def client_requirement() -> str:
    """``tactiled-client`` from clients/ beside this file if it is there, else the same version from an index."""
    version = tomllib.loads((HERE / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    if (CLIENTS / "pyproject.toml").is_file():
        return f"tactiled-client @ {CLIENTS.as_uri()}"
    return f"tactiled-client=={version}"


shutil.rmtree(HERE / "build" / "lib" / "tactiled_client", ignore_errors=True)
setup(install_requires=[*THIRD_PARTY, client_requirement()])
