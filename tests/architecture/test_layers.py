"""The house's rules, read from the code's own import statements (every ``import`` and ``from ...
import``, also those inside functions): ``registration``'s packages are layered, lower layers
never import higher ones, no module imports itself back through others, and the library never
imports the app or viser. In the app: the browser app (``app.gui``) never imports the command
line (``app.cli``), which starts it only from its ``app`` subcommand; views see the app only
through the context protocol (never the server), never import each other, and touch widgets
only through their panels. Each rule is checked by a function that a planted breach makes fail.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# registration's layers, bottom first: a module may import its own package and the layers below.
# The two stages of the paper on one layer (global registration, the local field) do not import
# each other.
LAYERS: list[tuple[str, ...]] = [
    ("coords", "mapping", "errors"),
    ("io",),
    ("geometry",),
    ("matching",),
    ("lens",),
    ("render",),
    ("global_registration", "local"),
    ("adjustment",),
    ("gis",),
    ("synth",),
    ("run",),
    ("traffic",),
    ("evaluation",),
]
RANK = {part: i for i, layer in enumerate(LAYERS) for part in layer}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(*roots: str) -> dict[str, Path]:
    return {_module_name(p): p for root in roots for p in sorted((REPO / root).rglob("*.py"))}


def _imports(path: Path, known: dict[str, Path]) -> dict[str, int]:
    """Modules of ``known`` (or any dotted name outside it) that ``path`` imports -> line.

    ``from pkg import sub`` where ``pkg.sub`` is a module is an import of that module (Python
    imports ``pkg`` on the way, but that is not a dependency of the code)."""
    out: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.setdefault(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                out.setdefault(sub if sub in known else node.module, node.lineno)
    return out


def _part(module: str) -> str | None:
    """The layer part of a registration module (``registration.lens.camera`` -> ``lens``)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "registration" and len(parts) > 1 else None


def test_every_registration_module_lies_in_a_layer():
    unplaced = sorted(
        m for m in _modules("registration") if m != "registration" and _part(m) not in RANK
    )
    assert unplaced == []


def test_lower_layers_never_import_higher_ones():
    mods = _modules("registration")
    wrong = []
    for name, path in mods.items():
        here = _part(name)
        if here is None:
            continue  # registration/__init__.py: load() opens a result (the run layer)
        for target, line in _imports(path, mods).items():
            there = _part(target)
            if there is None or there == here:
                continue
            if RANK[there] >= RANK[here]:
                wrong.append(f"{path.relative_to(REPO)}:{line} imports {target}")
    assert wrong == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_cycles_in_the_library_or_the_app():
    mods = _modules("registration", "app")
    graph: dict[str, set[str]] = defaultdict(set)
    for name, path in mods.items():
        graph[name] |= {t for t in _imports(path, mods) if t in mods and t != name}
    assert _cycles(graph) == []


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_library_never_imports_the_app_or_viser():
    mods = _modules("registration")
    wrong = [
        f"{path.relative_to(REPO)}:{line} imports {target}"
        for path in mods.values()
        for target, line in _imports(path, mods).items()
        if target.split(".")[0] in ("app", "viser")
    ]
    assert wrong == []
    # and importing every package of it loads neither
    code = (
        "import sys, registration, registration.run, registration.evaluation, registration.gis, "
        "registration.synth\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('app', 'viser'))\n"
        "print(bad)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"


# ------------------------------------------------------------------------------------------
# The app: the command line and the browser app apart, views behind the context protocol.

SHARED_VIEW_PARTS = ("base", "widgets", "cptable", "frames")
"""Modules of ``app.gui.views`` every view may use (not views themselves)."""
PANEL_MODULES = ("panel", "export_panel", "widgets")
"""Modules of ``app.gui.views`` that own viser widgets (the only ones that read their values)."""


def _under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _app_graph() -> dict[str, set[str]]:
    mods = _modules("app")
    return {name: set(_imports(path, mods)) for name, path in mods.items()}


def _breaches(
    graph: dict[str, set[str]], importer: str, forbidden: str, allowed: tuple[str, ...] = ()
) -> list[str]:
    """``"a imports b"`` for modules ``a`` under ``importer`` (but not in ``allowed``) that
    import a module under ``forbidden``."""
    return sorted(
        f"{a} imports {b}"
        for a, targets in graph.items()
        if _under(a, importer) and a not in allowed
        for b in targets
        if _under(b, forbidden)
    )


def _view_of(module: str) -> str | None:
    """The view a module belongs to (``app.gui.views.seed.panel`` -> ``seed``); None for the
    shared parts and modules outside the views."""
    parts = module.split(".")
    if parts[:3] != ["app", "gui", "views"] or len(parts) < 4 or parts[3] in SHARED_VIEW_PARTS:
        return None
    return parts[3]


def _views_importing_views(graph: dict[str, set[str]]) -> list[str]:
    return sorted(
        f"{a} imports {b}"
        for a, targets in graph.items()
        if _view_of(a) is not None
        for b in targets
        if _view_of(b) is not None and _view_of(b) != _view_of(a)
    )


def _widget_values(source: str) -> list[int]:
    """Lines where ``source`` reads or writes an attribute ``value`` or ``content`` (a raw viser
    handle's)."""
    return sorted(
        node.lineno
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Attribute) and node.attr in ("value", "content")
    )


def test_the_gui_never_imports_the_cli():
    graph = _app_graph()
    assert _breaches(graph, "app.gui", "app.cli") == []
    # The command line starts the browser app from its ``app`` subcommand only.
    assert _breaches(graph, "app.cli", "app.gui", allowed=("app.cli.commands.app",)) == []
    # What both share imports neither.
    shared = {
        m: t for m, t in graph.items() if not _under(m, "app.cli") and not _under(m, "app.gui")
    }
    assert _breaches(shared, "app", "app.cli") + _breaches(shared, "app", "app.gui") == []


def _views_importing_the_app(graph: dict[str, set[str]]) -> list[str]:
    """Views importing the server, or the package that hands it out (``from app.gui import
    App``): they see the app only as ``app.gui.context.ViewContext``."""
    wrong = _breaches(graph, "app.gui.views", "app.gui.server")
    wrong += [
        f"{a} imports app.gui"
        for a, targets in graph.items()
        if _under(a, "app.gui.views") and "app.gui" in targets
    ]
    return sorted(wrong)


def test_views_see_the_app_only_through_the_context():
    graph = _app_graph()
    assert _views_importing_the_app(graph) == []
    assert "app.gui.context" in graph["app.gui.views.base"]


def test_views_never_import_each_other():
    assert _views_importing_views(_app_graph()) == []


def test_views_touch_widgets_only_through_their_panels():
    wrong = [
        f"{path.relative_to(REPO)}:{line}"
        for name, path in _modules("app/gui/views").items()
        if name.split(".")[-1] not in PANEL_MODULES
        for line in _widget_values(path.read_text())
    ]
    assert wrong == []


def test_app_rules_find_planted_breaches():
    graph = {
        "app.gui.server": {"app.gui.views.seed.view", "app.cli.common"},
        "app.gui.views.seed.view": {"app.gui.server", "app.gui.views.sequence.scene"},
        "app.gui.views.seed.panel": {"app.gui.views.cptable.panel", "app.gui.views.widgets"},
        "app.cli.commands.app": {"app.gui"},
        "app.cli.commands.register": {"app.gui.project"},
        "app.client": {"app.gui"},
    }
    assert _breaches(graph, "app.gui", "app.cli") == ["app.gui.server imports app.cli.common"]
    assert _breaches(graph, "app.cli", "app.gui", allowed=("app.cli.commands.app",)) == [
        "app.cli.commands.register imports app.gui.project"
    ]
    assert _views_importing_the_app(graph) == ["app.gui.views.seed.view imports app.gui.server"]
    assert _views_importing_the_app({"app.gui.views.evaluate.view": {"app.gui"}}) == [
        "app.gui.views.evaluate.view imports app.gui"
    ]
    assert _views_importing_views(graph) == [
        "app.gui.views.seed.view imports app.gui.views.sequence.scene"
    ]
    assert _widget_values(
        "x = panel.gamma_slider.value\npanel.md.content = 'a'\ny = panel.gamma\n"
    ) == [
        1,
        2,
    ]
