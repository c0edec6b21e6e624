"""Which node parameters may change while the node runs: the rest are refused with a reason.

Every parameter of the stack's nodes is read once at start, into validated configuration; a
``param set`` on one of those would change nothing and say it did. So each node, at the end of its
constructor, names the few parameters it applies at run time (with a function that validates and
applies a new value) and every other change is refused, naming how to set it instead.
"""
from __future__ import annotations

from typing import Callable

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node

from drift_control.params import ParamError


def lock_parameters(node: Node, runtime: dict[str, Callable] | None = None) -> None:
    """Refuse run-time changes of every parameter but ``runtime`` (name -> apply(value)).

    ``apply`` raises ``ParamError`` (or ``ValueError``) to refuse a value; call this after all
    ``declare_parameter`` calls (rclpy runs the callback on declarations too).
    """
    runtime = dict(runtime or {})

    def on_set(params) -> SetParametersResult:
        for p in params:
            if p.name not in runtime:
                return SetParametersResult(
                    successful=False,
                    reason=f'{p.name} is read at start only; set it when starting the node '
                           f'(run_stack.py -p {node.get_name()}.{p.name}=VALUE)'
                           + (f'; changeable while running: {sorted(runtime)}' if runtime
                              else ''))
        for p in params:
            try:
                runtime[p.name](p.value)
            except (ParamError, ValueError, TypeError) as err:
                return SetParametersResult(successful=False, reason=f'{p.name}: {err}')
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
