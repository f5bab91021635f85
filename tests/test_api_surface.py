"""The public surface: every exported name imports, and the list is the one we ship."""

import hgsloc_plugin

EXPECTED = ["Camera", "GaussianScene", "HGSLocPlugin", "Pose", "QueryPrior", "RasterConfig", "RefineConfig",
            "RefineResult", "Renderer", "Tuning", "current_arch", "init", "render", "render_cost", "render_full"]


def test_all_names_import_and_match():
    assert sorted(hgsloc_plugin.__all__) == sorted(EXPECTED)
    for name in hgsloc_plugin.__all__:
        assert getattr(hgsloc_plugin, name) is not None


def test_subpackages_are_mapped():
    import hgsloc_plugin.adapters as a
    import hgsloc_plugin.kernels as k

    assert hasattr(a, "read_poses") and hasattr(k, "RasterConfig")
    assert hgsloc_plugin.init() in ("cpu", "cuda")


def test_pyproject_lists_every_subpackage():
    """A regular (non-editable) install ships only the packages listed in pyproject.toml."""
    from pathlib import Path

    import tomllib

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"hgsloc_plugin." + p.parent.relative_to(root / "hgsloc_plugin").as_posix().replace("/", ".")
             for p in (root / "hgsloc_plugin").rglob("__init__.py") if p.parent != root / "hgsloc_plugin"}
    assert found | {"hgsloc_plugin", "hgsloc_plugin.kernels", "hgsloc_plugin.adapters"} == listed
