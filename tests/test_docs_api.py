"""The API reference answers: the public names on one page with their signatures, ``__init__`` merged into the
class, Sphinx roles rendered as links (docs/hooks/sphinx_roles.py), and no machine paths in the docs.

The cheap checks read mkdocs.yml and the pages, and run the role rewriter on strings and on the real package
(griffe, about a second); one test builds the API page alone into a temporary folder (seconds) and reads its HTML.
"""

from __future__ import annotations

import importlib.util
import re
import shutil
from pathlib import Path

import griffe
import pytest
import yaml

import cuniform_torch
import precompute
import training

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
API_PAGE = DOCS / "api" / "toplevel.md"
HOOK = DOCS / "hooks" / "sphinx_roles.py"
BUILD_AND_DISTILL = [*(f"precompute.api.{n}" for n in precompute.__all__), *(f"training.api.{n}" for n in training.__all__),
                     "training.auto.auto_cuniform", "cuniform_torch.pytorch_mppi.MPPI",
                     "cuniform_torch.pytorch_mppi.MPPI_Batched"]
"""the page's names beyond ``cuniform_torch.__all__``: every public name of ``precompute`` and ``training`` (the
library's jobs), auto_cuniform, the pytorch_mppi drop-in"""
RAW_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|exc|obj|const):(?:`|<code>)")
MACHINE_PATH = re.compile(r"(?<![\w.~])/(?:tmp|root|work|home)/")


def _hook():
    spec = importlib.util.spec_from_file_location("sphinx_roles", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _AnyTag(yaml.SafeLoader):
    """mkdocs.yml's ``!!python/name:`` tags read as plain strings."""


_AnyTag.add_multi_constructor("tag:yaml.org,2002:python/", lambda loader, suffix, node: None)


def _config() -> dict:
    return yaml.load((ROOT / "mkdocs.yml").read_text(), Loader=_AnyTag)


def _python_options(config: dict) -> dict:
    plugin = next(p for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p)
    return plugin["mkdocstrings"]["handlers"]["python"]["options"]


def test_a_sphinx_role_becomes_an_autorefs_link():
    hook = _hook()
    text = hook.rewrite_roles("uses :class:`~cuniform_torch.controllers.core.MPPICore` and :func:`a.b.rollout`, "
                              ":meth:`the plan <MPPI.plan>`, :mod:`.grid`, :data:`X` and ``:class:``")
    assert '<autoref identifier="cuniform_torch.controllers.core.MPPICore" optional><code>MPPICore</code>' in text
    assert '<autoref identifier="a.b.rollout" optional><code>a.b.rollout</code></autoref>' in text
    assert '<autoref identifier="MPPI.plan" optional><code>the plan</code></autoref>' in text
    assert '<autoref identifier="grid" optional><code>grid</code></autoref>' in text
    assert text.endswith(" and ``:class:``")  # a role named in code is not a role
    assert not RAW_ROLE.search(text.removesuffix(" and ``:class:``")), text
    assert hook.rewrite_roles(":class:`~a.B`", lambda target: None) == "`B`"  # unresolvable: plain code


def test_the_extension_resolves_roles_in_the_real_package():
    """On cuniform_torch: no docstring keeps a role; a name is resolved from the docstring's own scope and a
    name the package exports points at the public page's entry."""
    loader = griffe.GriffeLoader(search_paths=[str(ROOT)], extensions=griffe.load_extensions(_hook().SphinxRoles))
    package = loader.load("cuniform_torch")
    mppi = package["controllers.mppi.MPPI"].docstring.value
    assert 'identifier="cuniform_torch.controllers.proposals.GaussianProposal"' in mppi, mppi
    top = package.docstring.value
    assert 'identifier="cuniform_torch.MPPICore" optional><code>MPPICore</code>' in top, top
    raw = [obj.path for obj in _hook().walk(package) if obj.docstring and RAW_ROLE.search(obj.docstring.value)]
    assert not raw, raw


def test_mkdocs_uses_the_extension_the_hook_and_the_options():
    config = _config()
    options = _python_options(config)
    assert any(str(ext).startswith("docs/hooks/sphinx_roles.py:SphinxRoles") for ext in options["extensions"])
    assert "docs/hooks/sphinx_roles.py" in config["hooks"]
    for key in ("merge_init_into_class", "show_signature_annotations", "separate_signature"):
        assert options.get(key) is True, key
    assert options["members_order"] == "source"
    assert "!^_" in options["filters"]
    api = next(entry["API"] for entry in config["nav"] if isinstance(entry, dict) and "API" in entry)
    assert api[0] == {"Public names": "api/toplevel.md"}, api[0]  # the public page first, modules after
    assert "[API reference](docs/api/toplevel.md)" in (ROOT / "README.md").read_text()


def test_the_api_page_documents_every_public_name():
    shown = re.findall(r"^::: ([\w.]+)$", API_PAGE.read_text(), flags=re.M)
    expected = [f"cuniform_torch.{name}" for name in cuniform_torch.__all__] + BUILD_AND_DISTILL
    assert sorted(shown) == sorted(expected)


def test_no_machine_paths_in_the_docs():
    pages = [ROOT / "README.md", *DOCS.rglob("*.md")]
    found = [f"{page.relative_to(ROOT)}:{n}" for page in pages
             for n, line in enumerate(page.read_text().splitlines(), 1) if MACHINE_PATH.search(line)]
    assert not found, found


def test_the_built_api_page_shows_parameters_and_no_raw_roles(tmp_path):
    """The public page alone, built with the site's mkdocs.yml into tmp_path: MPPI's constructor parameters
    are there, its cross-references are links, and no raw role is left."""
    build = pytest.importorskip("mkdocs.commands.build")
    from mkdocs.config import load_config

    docs = tmp_path / "docs"
    shutil.copytree(DOCS / "hooks", docs / "hooks")
    shutil.copytree(DOCS / "css", docs / "css")
    (docs / "api").mkdir()
    shutil.copy(API_PAGE, docs / "api" / "toplevel.md")
    config = load_config(str(ROOT / "mkdocs.yml"), docs_dir=str(docs), site_dir=str(tmp_path / "site"),
                         nav=[{"API": "api/toplevel.md"}], strict=False)
    build.build(config)
    html = (tmp_path / "site" / "api" / "toplevel" / "index.html").read_text()
    entry = html[html.index('id="cuniform_torch.MPPI"'):html.index('id="cuniform_torch.LogMPPI"')]
    signature = re.sub(r"<[^>]+>", "", entry)
    for parameter in ("num_samples", "horizon", "noise_std", "lambda_", "cost_fn", "seed"):
        assert parameter in signature, parameter
    assert 'href="#cuniform_torch.MPPICore"' in entry  # Bases: a link to the core's entry on the same page
    assert not RAW_ROLE.findall(html), RAW_ROLE.findall(html)[:5]
