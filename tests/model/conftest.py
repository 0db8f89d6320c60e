import importlib

import pytest

from relocfw.plugins import efficientnet_lite


@pytest.fixture
def without_efficientnet_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    """Behave as if relocfw[efficientnet] were not installed: importing either of its
    packages (architecture, weights) fails as a missing package does."""
    real = importlib.import_module

    def no_efficientnet(name: str, *args: object) -> object:
        if name.startswith("efficientnet_lite"):
            raise ImportError(name)
        return real(name, *args)

    monkeypatch.setattr(efficientnet_lite.importlib, "import_module", no_efficientnet)
