"""Write the parameter reference of every node from the nodes' own declarations.

    python -m soft_gripper_sdre.tools.params_doc [--out docs/parameters.md]

Each node module declares its parameters once (``PARAMS``: name, default, description, units,
range, choices, read-only); this tool renders them as Markdown tables, so the reference cannot
drift from the code (a test compares the shipped page with a fresh rendering).
"""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path
import sys

from soft_gripper_sdre.nodes.params import Param

NODES = ('simulator', 'estimator', 'trajectory', 'controller', 'recorder', 'excitation',
         'plant_driver', 'mocap_tips')
DEFAULT_OUT = Path('docs/parameters.md')


def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _number(value) -> str:
    return str(value) if isinstance(value, int) else f'{value:g}'


def _limits(p: Param) -> str:
    if p.choices:
        return ', '.join(f'`{c}`' for c in p.choices)
    if p.min is None and p.max is None:
        return ''
    lo = '−∞' if p.min is None else _number(p.min)
    hi = '∞' if p.max is None else _number(p.max)
    return f'[{lo}, {hi}]'


def node_table(node: str) -> str:
    """One node's parameters as a Markdown table."""
    module = importlib.import_module(f'soft_gripper_sdre.nodes.{node}')
    rows = ['| parameter | default | units | range or choices | runtime | meaning |',
            '| --- | --- | --- | --- | :---: | --- |']
    for p in module.PARAMS:
        default = f'`{p.default!r}`' if p.default != '' else "`''`"
        rows.append(f'| `{p.name}` | {_cell(default)} | {_cell(p.units)} | {_cell(_limits(p))} | '
                    f'{"" if p.read_only else "yes"} | {_cell(p.description)} |')
    summary = ((module.__doc__ or '').strip().splitlines() or [''])[0]
    return f'## {node}\n\n{summary}\n\n' + '\n'.join(rows) + '\n'


def render() -> str:
    """The whole parameter reference page."""
    head = ('# Node parameters\n\n'
            'Generated from the nodes\' declarations by '
            '`python -m soft_gripper_sdre.tools.params_doc`; do not edit by hand. Every node also '
            'prints its table with `--help`.\n\n'
            'Values come from `config/<node>.yaml` (keys `/**/<node>`, so they apply in any '
            'namespace), `--params-file` or `-p name:=value`. A bad value stops the node at '
            'start-up with a message naming the parameter (exit status 2); so does a value of '
            'the wrong type, or a key the node does not declare, in its section of a parameters '
            'file, naming the key, the node and the file. Parameters marked '
            '"runtime" can be changed with `ros2 param set`; a refused change returns its reason '
            'and the old value stays in force. Units are SI.\n\n')
    return head + '\n'.join(node_table(n) for n in NODES)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m soft_gripper_sdre.tools.params_doc',
                                 description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=DEFAULT_OUT,
                    help='output file (default %(default)s); - for stdout')
    a = ap.parse_args(argv)
    text = render()
    if str(a.out) == '-':
        sys.stdout.write(text)
    else:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text, encoding='utf-8')
        print(f'wrote {a.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
