"""Packaging beyond pyproject.toml: the top-level ``pipelines/`` folder ships as the package ``hoidata.presets``,
so an installed ``hoidata`` finds its named pipelines (``hoidata.sections.pipelines_dir``)."""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["hoidata*", "hoisdf*"]) + ["hoidata.presets"],
    package_dir={"hoidata.presets": "pipelines"},
    package_data={"hoidata.presets": ["*.toml"]},
)
