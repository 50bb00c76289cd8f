"""The architecture, pinned: what each part may import, read from every module's source and
checked again by importing every module in a fresh interpreter.

- The core (`kneeseat_core`) imports nothing of ROS: no rclpy, message package, mcap or
  `kneeseat_ros`, at module level or inside a function.
- Its subpackages import downwards only (`ALLOWED`): the shared modules at the top import
  no subpackage; the table code imports no settle, mesh, knee or sweep code; the referee
  nothing of the settle (it judges the settle, so it must share no code with it).
- The node (`kneeseat_ros.table_server` and what it loads) touches no mesh and no collision
  query: no trimesh, no python-fcl, nothing of the settle or the sweep.
- No two modules import each other, directly or around a loop.
"""
from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path
import subprocess
import sys

import pytest

from conftest import REPO

CORE = REPO / 'kneeseat_core'
ROS = REPO / 'kneeseat_ros'
# top-level names that are ROS: a core module may not import any of them
ROS_NAMES = ('rclpy', 'rosidl_runtime_py', 'rosidl_parser', 'builtin_interfaces', 'std_msgs',
             'geometry_msgs', 'sensor_msgs', 'visualization_msgs', 'diagnostic_msgs',
             'std_srvs', 'tf2_msgs', 'rcl_interfaces', 'mcap', 'mcap_ros2', 'kneeseat_ros')
# which parts of the core each part may import ('' is the shared modules at the top)
ALLOWED = {
    '': {''},
    'meshes': {'', 'meshes'},
    'table': {'', 'table'},
    'knee': {'', 'knee', 'meshes'},
    'settle': {'', 'settle', 'meshes'},
    'referee': {'', 'referee', 'meshes', 'knee', 'table'},
    'sweep': {'', 'sweep', 'meshes', 'knee', 'settle', 'table'},
    'report': {'', 'report', 'meshes', 'knee', 'table'},
    'cli': {'', 'cli', 'meshes', 'knee', 'settle', 'referee', 'table', 'sweep', 'report'},
}


def module_name(path: Path) -> str:
    """`kneeseat_core/settle/climb.py` -> `kneeseat_core.settle.climb` (packages by name)."""
    parts = list(path.relative_to(REPO).with_suffix('').parts)
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def modules(root: Path) -> list[Path]:
    """Every Python module of a package, sorted."""
    return sorted(root.rglob('*.py'))


def is_module(dotted: str) -> bool:
    """Whether a dotted name is one of the project's modules or packages (a compiled module
    counts by its type stub, `.pyi`)."""
    path = REPO.joinpath(*dotted.split('.'))
    return path.with_suffix('.py').is_file() or path.with_suffix('.pyi').is_file() \
        or (path / '__init__.py').is_file()


def imports(path: Path) -> Iterator[str]:
    """Every module `path` imports, anywhere in it (function-level imports included), as an
    absolute dotted name. `from X import y` is the submodule `X.y` when there is one (then
    X is only its parent, already loading), else X; outside the project both are given."""
    tree = ast.parse(path.read_text())
    name = module_name(path)
    package = name.split('.') if path.name == '__init__.py' else name.split('.')[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ''
            for alias in node.names:
                sub = f'{target}.{alias.name}'
                if not is_module(target):
                    yield from (target, sub)
                else:
                    yield sub if is_module(sub) else target


def part(dotted: str) -> str | None:
    """The part of the core a dotted name belongs to ('' for the shared top-level modules),
    None outside the core."""
    bits = dotted.split('.')
    if bits[0] != 'kneeseat_core':
        return None
    # `python -m kneeseat_core` and the `kneeseat` program run the command line; the
    # program's module sits outside `cli`, whose package loads numpy, so that it can set
    # OpenBLAS's thread count before numpy loads
    if bits[1:2] in (['__main__'], ['console']):
        return 'cli'
    if len(bits) == 1 or not (CORE / bits[1]).is_dir():
        return ''
    return bits[1]


def loaded_after_import(names: list[str]) -> set[str]:
    """The modules a fresh interpreter has loaded after importing `names`."""
    code = (f'import importlib, sys\nfor n in {names!r}:\n    importlib.import_module(n)\n'
            'print("\\n".join(sorted(sys.modules)))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, cwd=REPO)
    return set(out.stdout.split())


CORE_MODULES = [module_name(p) for p in modules(CORE) if p.name != '__main__.py']


def test_the_core_names_no_ros_module_anywhere_in_its_source() -> None:
    found = [(module_name(p), target) for p in modules(CORE) for target in imports(p)
             if target.split('.')[0] in ROS_NAMES]
    assert not found, f'core modules import ROS: {sorted(set(found))}'


def test_importing_every_core_module_loads_nothing_of_ros() -> None:
    loaded = loaded_after_import(CORE_MODULES)
    assert not {m for m in loaded if m.split('.')[0] in ROS_NAMES}


@pytest.mark.parametrize('path', modules(CORE), ids=lambda p: module_name(p))
def test_each_part_of_the_core_imports_downwards_only(path: Path) -> None:
    here = part(module_name(path))
    assert here is not None and here in ALLOWED, f'{path}: a part of the core ALLOWED lacks'
    wrong = sorted({target for target in imports(path)
                    if part(target) is not None and part(target) not in ALLOWED[here]})
    assert not wrong, (f'{module_name(path)} ({here or "top"}) imports {wrong}; it may use '
                       f'only {sorted(p or "top" for p in ALLOWED[here])}')


@pytest.mark.parametrize('package, forbidden', [
    ('kneeseat_core.table', ('kneeseat_core.settle', 'kneeseat_core.meshes',
                             'kneeseat_core.sweep', 'kneeseat_core.knee', 'trimesh', 'fcl')),
    ('kneeseat_core.referee', ('kneeseat_core.settle', 'kneeseat_core.sweep')),
    ('kneeseat_ros.table_server', ('trimesh', 'fcl', 'kneeseat_core.settle',
                                   'kneeseat_core.sweep', 'kneeseat_core.meshes')),
])
def test_a_part_loads_nothing_it_must_not_use(package: str, forbidden: tuple[str, ...]) -> None:
    loaded = loaded_after_import([package])
    bad = sorted(m for m in loaded if any(m == f or m.startswith(f + '.') for f in forbidden))
    assert not bad, f'importing {package} loads {bad}'


def test_no_two_modules_import_each_other() -> None:
    """No loop in the graph of explicit imports between the project's modules (a package's
    __init__ importing its own submodules is an edge like any other)."""
    paths = modules(CORE) + modules(ROS)
    names = {module_name(p) for p in paths}
    graph = {module_name(p): {t for t in imports(p) if t in names and t != module_name(p)}
             for p in paths}
    state: dict[str, int] = {}        # 1 on the current path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (loop := visit(nxt)):
                return loop
        state[node] = 2
        path.pop()
        return None

    for start in sorted(graph):
        if start not in state and (loop := visit(start)):
            pytest.fail('import loop: ' + ' -> '.join(loop))


def test_no_package_folder_is_a_list() -> None:
    """A folder of more than 15 modules is a list, not a map."""
    for root in (CORE, ROS):
        for folder in [root, *(p for p in root.rglob('*') if p.is_dir()
                               and (p / '__init__.py').exists())]:
            count = len(list(folder.glob('*.py')))
            assert count <= 15, f'{folder.relative_to(REPO)} holds {count} modules'
