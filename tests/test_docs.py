"""The Sphinx reference covers the public API: every ``ws.*`` name is documented on the page of
the sub-package it lives in (``.. automodule:: warpsim.PACKAGE`` documents that package's
``__all__``), every sub-package with an ``__all__`` has a page, the guide has a tutorial per domain,
and every picture and example a page includes exists. (``.ci/run`` builds the pages with
``sphinx -W``: warnings are errors.)"""

import importlib
import pathlib
import re

import warpsim

DOCS = pathlib.Path(__file__).resolve().parents[1] / "docs"
TUTORIALS = ("bodies", "cloth", "fluids", "agents", "worlds", "viewer", "differentiable")


def documented_modules():
    mods = set()
    for page in (DOCS / "api").glob("*.rst"):
        mods.update(re.findall(r"^\.\. automodule:: ([\w.]+)", page.read_text(), re.M))
    return mods


def test_every_public_name_is_on_its_package_page():
    pages = [importlib.import_module(m) for m in documented_modules()]
    missing = []
    for name in warpsim.__all__:
        if name == "__version__":
            continue
        obj = getattr(warpsim, name)
        if not any(name in getattr(m, "__all__", ()) and getattr(m, name) is obj for m in pages):
            missing.append(name)
    assert not missing, f"ws.* names without a reference entry: {missing}"


def test_every_sub_package_with_entry_names_has_a_page():
    mods = documented_modules()
    pkg = pathlib.Path(warpsim.__file__).parent
    undocumented = []
    for init in sorted(pkg.glob("*/__init__.py")):
        name = f"warpsim.{init.parent.name}"
        if name in ("warpsim.kernels", "warpsim.distributed"):
            continue  # Warp code only; distributed documents its entry function on the worlds page
        if "__all__" in init.read_text() and name not in mods:
            undocumented.append(name)
    assert not undocumented, f"sub-packages without an API page: {undocumented}"


def test_guide_pages_and_what_they_include_exist():
    index = (DOCS / "index.rst").read_text()
    assert "getting_started" in index and all(f"tutorials/{t}" in index for t in TUTORIALS)
    for page in [DOCS / "getting_started.rst", *(DOCS / "tutorials" / f"{t}.rst" for t in TUTORIALS)]:
        text = page.read_text()
        for target in re.findall(r"^\.\. (?:image|literalinclude):: (\S+)", text, re.M):
            assert (page.parent / target).resolve().is_file(), f"{page.name}: {target} does not exist"
    pictures = {p.name for t in TUTORIALS for p in [DOCS / "tutorials" / f"{t}.rst"]
                for p in map(pathlib.Path, re.findall(r"^\.\. image:: (\S+)", p.read_text(), re.M))}
    assert len(pictures) >= 15  # the domains' gallery clips
