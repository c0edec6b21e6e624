"""The codebase's own rules: algorithm modules never import ROS; nodes live under nodes/."""
import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'
ROS_MODULES = {'rclpy', 'drift_msgs', 'std_msgs', 'nav_msgs', 'diagnostic_msgs', 'rosgraph_msgs',
               'builtin_interfaces', 'geometry_msgs', 'std_srvs'}
CORE_FILES = sorted(p for p in SRC.glob('*/*/**/*.py') if 'nodes' not in p.parts)


def imported_roots(path: Path) -> set[str]:
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split('.')[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split('.')[0])
    return roots


def test_there_are_core_modules_to_check():
    assert len(CORE_FILES) >= 5


@pytest.mark.parametrize('path', CORE_FILES, ids=lambda p: str(p.relative_to(SRC)))
def test_core_module_imports_no_ros(path):
    assert not imported_roots(path) & ROS_MODULES, f'{path} imports ROS outside nodes/'
