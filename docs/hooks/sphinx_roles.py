"""The docs site's cross-references: Sphinx roles in docstrings become links.

The code's docstrings are written with Sphinx roles (``:class:`~cuniform_torch.controllers.core.MPPICore```,
``:func:`rollout```, ``:meth:`MPPI.command```, ``:mod:``, ``:attr:``, ``:data:``, ...), which mkdocstrings does not
read: without this module they reach the page as raw text. Two plug-ins, one file:

* :class:`SphinxRoles`, a griffe extension (mkdocs.yml, ``mkdocstrings`` python handler ``extensions``): once a
  package is loaded, every docstring's roles are rewritten into optional autorefs cross-references. The target is
  resolved as Python would from the docstring's own scope (``MPPICore`` inside ``cuniform_torch`` is
  ``cuniform_torch.controllers.core.MPPICore``), then pointed at the public name where ``cuniform_torch`` exports
  one (the top-level API page). ``~`` shows the last part only, as in Sphinx; ``title <target>`` shows the title.
  A target no page documents (a private helper, torch) renders as plain code, without a warning.
* :func:`on_post_page`, a mkdocs hook (mkdocs.yml ``hooks``): a built page that still shows a raw role is a
  warning, so ``mkdocs build --strict`` (CI) fails on it.
"""

from __future__ import annotations

import html
import logging
import re
from collections.abc import Callable, Iterator
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?P<role>class|func|meth|mod|attr|data|exc|obj|const|type):`(?P<body>[^`]+)`")
RAW_ROLE_HTML = re.compile(r":(?:py:)?(?:class|func|meth|mod|attr|data|exc|obj|const|type):(?:<code>|`)")
PUBLIC_PACKAGE = "cuniform_torch"  # its __init__ exports the names the API page documents

log = logging.getLogger("mkdocs.hooks.sphinx_roles")


def split_role(body: str) -> tuple[str, str]:
    """``(title, target)`` of a role's text: ``~a.b.C`` -> ``("C", "a.b.C")``, ``a.b.C`` -> ``("a.b.C", "a.b.C")``,
    ``the core <a.b.C>`` -> ``("the core", "a.b.C")``; a leading ``.`` or ``!`` of the target is dropped."""
    body = body.strip()
    explicit = re.fullmatch(r"(?P<title>.*?)\s*<(?P<target>[^<>]+)>", body, flags=re.S)
    if explicit:
        return explicit["title"], explicit["target"].strip().lstrip(".!~")
    target = body.lstrip("!")
    shortened = target.startswith("~")
    target = target.lstrip("~.")
    return (target.rsplit(".", 1)[-1] if shortened else target), target


def rewrite_roles(text: str, resolve: Callable[[str], str | None] = lambda target: target) -> str:
    """``text`` with every Sphinx role made a cross-reference: an autorefs ``<autoref ... optional>`` around the
    title as code when ``resolve(target)`` gives an identifier, the title as plain code when it gives None."""

    def replace(match: re.Match[str]) -> str:
        title, target = split_role(match["body"])
        identifier = resolve(target)
        if not identifier:
            return f"`{title}`"
        return f'<autoref identifier="{html.escape(identifier)}" optional><code>{html.escape(title)}</code></autoref>'

    return ROLE.sub(replace, text)


class SphinxRoles(griffe.Extension):
    """Griffe extension: rewrites the Sphinx roles of every docstring of a loaded package (see the module)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        collection = loader.modules_collection
        public = public_names(collection)
        for obj in walk(pkg):
            if obj.docstring is not None and ROLE.search(obj.docstring.value):
                obj.docstring.value = rewrite_roles(obj.docstring.value, resolver(obj, collection, public))


def walk(obj: griffe.Object) -> Iterator[griffe.Object]:
    """``obj`` and its own members, depth first (aliases skipped: their targets are walked where defined)."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from walk(member)  # type: ignore[arg-type]


def public_names(collection: griffe.ModulesCollection) -> dict[str, str]:
    """``{canonical path: public path}`` of the names ``cuniform_torch`` exports (empty before it is loaded)."""
    if PUBLIC_PACKAGE not in collection.members:
        return {}
    package = collection.members[PUBLIC_PACKAGE]
    exported = package.exports or ()
    names = {}
    for name in exported:
        member = package.members.get(str(name))
        if member is not None and member.is_alias:
            names[canonical(member)] = f"{PUBLIC_PACKAGE}.{name}"
    return names


def canonical(obj: griffe.Object | griffe.Alias) -> str:
    """Where ``obj`` is defined: an alias followed as far as the loaded packages go."""
    if not obj.is_alias:
        return obj.path
    try:
        return obj.final_target.path
    except (griffe.AliasResolutionError, griffe.CyclicAliasError):
        return obj.target_path  # type: ignore[union-attr]


def lookup(collection: griffe.ModulesCollection, path: str) -> str | None:
    """The canonical path of ``path`` if a loaded package has it, without resolving aliases to other packages."""
    try:
        obj = collection.get_member(path)
    except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None
    return canonical(obj)


def resolver(obj: griffe.Object, collection: griffe.ModulesCollection,
             public: dict[str, str]) -> Callable[[str], str | None]:
    """The identifier a role's target names from ``obj``'s docstring: a full dotted path as is, else its first
    part resolved in ``obj``'s scope (members and imports, then the enclosing scopes); made canonical where the
    object is loaded, then public (``cuniform_torch.X``, and its members) where ``cuniform_torch`` exports it."""

    def resolve(target: str) -> str | None:
        path = lookup(collection, target)
        if path is None:
            first, _, rest = target.partition(".")
            try:
                base = obj.resolve(first)  # members and imports, then the enclosing scopes
            except griffe.NameResolutionError:
                base = first
            full = f"{base}.{rest}" if rest else base
            path = lookup(collection, full) or full
        for canonical, name in public.items():
            if path == canonical or path.startswith(canonical + "."):
                return name + path[len(canonical):]
        return path

    return resolve


def on_post_page(output: str, *, page: Any, config: Any) -> str:
    """mkdocs hook: warn (an error under ``--strict``) when a built page still shows a raw Sphinx role."""
    found = RAW_ROLE_HTML.findall(output)
    if found:
        log.warning("%s: %d raw Sphinx role(s) in the built page, e.g. %r (docs/hooks/sphinx_roles.py rewrites "
                    "them in docstrings; write a Markdown link in a page)", page.file.src_uri, len(found), found[0])
    return output
