#!/usr/bin/env python3
"""Write tests/module_seconds.json from a pytest JUnit XML report: the seconds each test module
took (setup, call and teardown of its tests), which tests/conftest.py uses to hand the heaviest
modules to the pytest-xdist workers first.

    make test                                   # writes build/test-results.xml
    python3 tools/test-weights.py build/test-results.xml > tests/module_seconds.json
"""
from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: test-weights.py REPORT.xml", file=sys.stderr)
        return 2
    seconds: dict[str, float] = defaultdict(float)
    for case in ET.parse(argv[0]).getroot().iter("testcase"):
        module = case.get("classname", "").split(".")
        while module and not module[-1].startswith("test_"):    # a class inside the module
            module.pop()
        if module:
            seconds["/".join(module) + ".py"] += float(case.get("time", 0.0))
    ordered = dict(sorted(((k, round(v, 1)) for k, v in seconds.items()), key=lambda kv: -kv[1]))
    json.dump(ordered, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
