#!/usr/bin/env python3
"""Generates the Python gRPC stubs of the mpiflow API from the repo's proto/ with grpcio-tools.

    python clients/python/gen_stubs.py            # (re)write clients/python/mpiflow/_proto/
    python clients/python/gen_stubs.py --check    # exit 1 if the committed stubs differ

The stubs are committed (so `pip install ./clients/python` needs no grpcio-tools);
tests/test_stubs.py runs the check. The proto is compiled under its canonical name
(`mpiflow/v1/mpiflow.proto`, as every other language sees it) and the three generated files are
placed flat in mpiflow/_proto/, with the one absolute import of the gRPC module made relative
(`mpiflow.v1` would otherwise resolve to this package, named `mpiflow` too).
"""
from __future__ import annotations

import argparse
import difflib
import os
import re
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROTO_ROOT = HERE.parent.parent / "proto"
PROTO_FILE = "mpiflow/v1/mpiflow.proto"
OUT_DIR = HERE / "mpiflow" / "_proto"
GENERATED = ("mpiflow_pb2.py", "mpiflow_pb2.pyi", "mpiflow_pb2_grpc.py")
_IMPORT_RE = re.compile(r"^from mpiflow\.v1 import mpiflow_pb2 as ", re.M)


def generate(proto_root: Path = PROTO_ROOT) -> dict[str, bytes]:
    """Runs protoc (grpc_tools) and returns {file name: content} of the flat stubs."""
    from grpc_tools import protoc  # grpcio-tools: a development dependency only

    include = os.path.join(os.path.dirname(protoc.__file__), "_proto")
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "grpc_tools.protoc",
            f"-I{proto_root}",
            f"-I{include}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            f"--grpc_python_out={tmp}",
            PROTO_FILE,
        ]
        rc = protoc.main(args)
        if rc != 0:
            raise RuntimeError(f"protoc failed ({rc}): {' '.join(args)}")
        out = {}
        gen = Path(tmp) / "mpiflow" / "v1"
        for name in GENERATED:
            data = (gen / name).read_bytes()
            if name == "mpiflow_pb2_grpc.py":
                text, n = _IMPORT_RE.subn("from . import mpiflow_pb2 as ", data.decode("utf-8"))
                if n != 1:
                    raise RuntimeError("unexpected import layout in the generated gRPC module")
                data = text.encode("utf-8")
            out[name] = data
        return out


def check(out_dir: Path = OUT_DIR) -> list[str]:
    """Returns the differences (unified diffs) between fresh stubs and those in out_dir."""
    problems = []
    for name, fresh in generate().items():
        path = out_dir / name
        old = path.read_bytes() if path.exists() else b""
        if old != fresh:
            diff = difflib.unified_diff(
                old.decode("utf-8", "replace").splitlines(),
                fresh.decode("utf-8", "replace").splitlines(),
                f"committed/{name}",
                f"generated/{name}",
                lineterm="",
                n=1,
            )
            lines = [ln if len(ln) <= 160 else ln[:157] + "..." for ln in diff]
            problems.append("\n".join(lines[:40]))
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    a = ap.parse_args()
    if a.check:
        problems = check()
        for p in problems:
            print(p)
        if problems:
            print("stubs are stale: run python clients/python/gen_stubs.py", file=sys.stderr)
            return 1
        print("stubs are up to date")
        return 0
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    for name, data in generate().items():
        (OUT_DIR / name).write_bytes(data)
        print(f"wrote {OUT_DIR / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
