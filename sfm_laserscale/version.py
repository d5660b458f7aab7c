"""The package's one version string: ``sfm-laserscale --version``, report.json's ``version``,
the package metadata (pyproject.toml reads it) and the Docker image's label (docker/Dockerfile's
VERSION, checked against it by tests/test_docker.py)."""

__version__ = "0.1.0"
