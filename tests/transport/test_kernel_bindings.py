"""The one table of foreign-function signatures (scene/_bindings.py): no ctypes signature is
declared anywhere else in the package, the kernel's table agrees with the prototypes of
``transport/csrc/kernel.h`` and with what the built library exports, and the build's cache name
covers every source file, the flags and the sanitizer."""

from __future__ import annotations

import ast
import ctypes
import re
import shutil
import subprocess
from pathlib import Path

import pytest

import torch_brdf
from torch_brdf.errors import TorchBRDFError
from torch_brdf.scene import _bindings
from torch_brdf.scene._bindings import EMBREE, KERNEL, declare
from torch_brdf.transport import _native

PACKAGE = Path(torch_brdf.__file__).parent
BINDINGS = Path(_bindings.__file__)
HEADER = PACKAGE / "transport" / "csrc" / "kernel.h"
_SIGNATURE_ATTRS = {"argtypes", "restype"}
_PROTOTYPES = {"CFUNCTYPE", "PYFUNCTYPE", "WINFUNCTYPE"}


def signatures(source: str) -> list[str]:
    """Where ``source`` declares a ctypes signature: an assignment to ``.argtypes`` or
    ``.restype`` (plain, augmented, annotated, in a tuple, or by ``setattr``) or a function
    prototype (``CFUNCTYPE``, ``PYFUNCTYPE``, ``WINFUNCTYPE``), as ``"line N: what"``."""
    found = []

    def targets(node: ast.AST) -> list[ast.AST]:
        if isinstance(node, (ast.Tuple, ast.List)):
            return [t for e in node.elts for t in targets(e)]
        return [node]

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assign):
            tgts = [t for x in node.targets for t in targets(x)]
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            tgts = [node.target]
        else:
            tgts = []
        for t in tgts:
            if isinstance(t, ast.Attribute) and t.attr in _SIGNATURE_ATTRS:
                found.append(f"line {node.lineno}: .{t.attr} =")
        if isinstance(node, ast.Call):
            fn = node.func
            name = fn.attr if isinstance(fn, ast.Attribute) else fn.id if isinstance(fn, ast.Name) else ""
            if name in _PROTOTYPES:
                found.append(f"line {node.lineno}: {name}(...)")
            if name == "setattr" and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant):
                if node.args[1].value in _SIGNATURE_ATTRS:
                    found.append(f"line {node.lineno}: setattr(., {node.args[1].value!r}, .)")
        if isinstance(node, ast.ImportFrom) and node.module == "ctypes":
            for a in node.names:
                if a.name in _PROTOTYPES:
                    found.append(f"line {node.lineno}: imports {a.name}")
    return found


def test_the_checker_finds_every_form_of_signature():
    src = """
import ctypes
from ctypes import CFUNCTYPE
lib.f.restype = ctypes.c_int
lib.g.restype, lib.g.argtypes = None, [ctypes.c_void_p]
fn.argtypes += [ctypes.c_int]
setattr(lib.h, "argtypes", [])
proto = ctypes.CFUNCTYPE(None, ctypes.c_int)
cb = ctypes.PYFUNCTYPE(None)
x.restype: object = None
"""
    found = signatures(src)
    assert sorted(int(f.split(":")[0][5:]) for f in found) == [3, 4, 5, 5, 6, 7, 8, 9, 10], found
    # reading a signature, or calling a function without declaring one, is not declaring
    assert signatures("import ctypes\nprint(lib.f.restype)\nctypes.CDLL(None).prctl(1, 15, 0, 0, 0)\n") == []


def test_no_ctypes_signature_outside_the_bindings_module():
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == BINDINGS:
            continue
        offenders += [f"{path.relative_to(PACKAGE.parent)} {f}" for f in signatures(path.read_text(encoding="utf-8"))]
    assert not offenders, "ctypes signatures belong in torch_brdf/scene/_bindings.py:\n  " + "\n  ".join(offenders)
    # declare(): the one line that sets both
    assert len({f.split(":")[0] for f in signatures(BINDINGS.read_text(encoding="utf-8"))}) == 1


_C_TYPES = {"int64_t": ctypes.c_int64, "int": ctypes.c_int, "float": ctypes.c_float, "double": ctypes.c_double}


def header_prototypes(text: str) -> dict[str, tuple[str, list[str]]]:
    """``TB_API`` prototypes of a header: name -> (return type, parameter types), the parameter
    names dropped and whitespace collapsed (``const float *``, ``int64_t``, ...)."""
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    out = {}
    for ret, name, params in re.findall(r"TB_API\s+(?:TB_SIMD\s+)?([\w\s\*]+?)\s*\b(tb_\w+)\s*\(([^)]*)\)\s*;", text):
        types = []
        for p in params.split(","):
            p = " ".join(p.replace("*", " * ").split())
            types.append(re.sub(r"\s*\b\w+$", "", p).replace(" *", "*") if p != "void" else "")
        out[name] = (" ".join(ret.replace("*", " * ").split()).replace(" *", "*"), [t for t in types if t])
    return out


def _matches(ctype, c: str) -> bool:
    if c.endswith("*"):  # any pointer: c_void_p, or a typed pointer the entry writes through
        return ctype is ctypes.c_void_p or (isinstance(ctype, type) and issubclass(ctype, ctypes._Pointer))
    if c == "void":
        return ctype is None
    return _C_TYPES.get(c.replace("const ", "")) is ctype


def test_kernel_table_matches_the_header():
    protos = header_prototypes(HEADER.read_text(encoding="utf-8"))
    assert len(protos) == 43
    assert sorted(protos) == sorted(KERNEL), (
        f"header only: {set(protos) - set(KERNEL)}; table only: {set(KERNEL) - set(protos)}"
    )
    for name, (ret, params) in protos.items():
        restype, argtypes = KERNEL[name]
        assert _matches(restype, ret), f"{name}: returns {ret}, table says {restype}"
        assert len(argtypes) == len(params), f"{name}: {len(params)} parameters, table has {len(argtypes)}"
        for i, (a, c) in enumerate(zip(argtypes, params, strict=True)):
            assert _matches(a, c), f"{name}: parameter {i} is {c}, table says {a}"


def test_header_check_catches_a_wrong_table_row():
    protos = header_prototypes("TB_API int64_t tb_x(void *s, const float *o, int64_t n, float eps);\n")
    assert protos == {"tb_x": ("int64_t", ["void*", "const float*", "int64_t", "float"])}
    assert not _matches(ctypes.c_int, "int64_t") and not _matches(ctypes.c_double, "float")
    assert _matches(ctypes.POINTER(ctypes.c_int64), "int64_t*") and not _matches(ctypes.c_int64, "int64_t*")


LIB = _native.library()
needs_cc = pytest.mark.skipif(LIB is None, reason="no C compiler here: only the torch path runs")


@needs_cc
def test_loaded_kernel_has_the_table_signatures():
    for name, (restype, argtypes) in KERNEL.items():
        fn = getattr(LIB, name)
        assert fn.restype is restype and list(fn.argtypes) == list(argtypes), name


@needs_cc
@pytest.mark.skipif(shutil.which("nm") is None, reason="no nm (binutils) to list the library's symbols")
def test_built_library_exports_exactly_the_entry_points():
    res = subprocess.run(["nm", "-D", "--defined-only", LIB._name], capture_output=True, text=True, check=True)
    names = {line.split()[-1] for line in res.stdout.splitlines() if line.split()}
    entries = {n for n in names if n.startswith("tb_") and "." not in n}  # not the ifunc resolvers
    assert entries == set(KERNEL)
    if "sanitize" not in Path(LIB._name).name:  # the sanitizers' runtime hooks are exported too
        assert {n.split(".")[0] for n in names} == set(KERNEL), sorted(names - set(KERNEL))


def test_declare_refuses_a_library_without_an_entry():
    libc = ctypes.CDLL(None)
    with pytest.raises(AttributeError):
        declare(libc, {"tb_no_such_entry": (None, [])})
    assert set(EMBREE) == {"rtcGetSceneDevice", "rtcReleaseDevice"}


def test_build_name_covers_every_source_flags_and_sanitizer(tmp_path):
    src = tmp_path / "csrc"
    shutil.copytree(HEADER.parent, src)
    files = sorted(src.iterdir())
    assert {f.suffix for f in files} == {".c", ".h"} and len(files) == len(_native.sources())
    cc, flags = ["cc"], list(_native._FLAGS)
    base = _native.build_name(cc, flags, files)
    assert base.startswith("polynomial_") and base == _native.build_name(cc, flags, files)
    names = {base}
    for f in files:  # one byte more in any file, the header included: another build
        text = f.read_bytes()
        f.write_bytes(text + b"\n")
        names.add(_native.build_name(cc, flags, files))
        f.write_bytes(text)
    assert len(names) == len(files) + 1
    assert _native.build_name(cc, flags, files) == base
    assert _native.build_name(cc, [*flags, "-DX"], files) != base
    assert _native.build_name(["gcc-12"], flags, files) != base
    sanitized = _native.build_name(cc, [*flags, *_native.SANITIZE_FLAGS], files, sanitize=True)
    assert sanitized.startswith("polynomial_sanitize_") and sanitized[20:] != base[11:]
    assert {"-Wall", "-Wextra", "-Werror"} <= set(flags)


def test_sanitized_kernel_without_its_runtime_is_refused(monkeypatch, tmp_path):
    """Loading an ASan build into a process without the runtime would abort it: a clear error
    instead, before any compiling."""
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    monkeypatch.setenv(_native.SANITIZE_ENV_VAR, "1")
    monkeypatch.setattr(_native, "_state", {"lib": None, "tried": False, "build_s": 0.0})
    monkeypatch.setattr(_native, "_compiler", lambda: ["cc"])
    monkeypatch.setattr(_native, "_asan_loaded", lambda: False)
    monkeypatch.setattr(_native, "sanitizer_runtime", lambda cc=None: "/path/to/libasan.so")
    with pytest.raises(TorchBRDFError, match=r"LD_PRELOAD=/path/to/libasan\.so"):
        _native.library()
    assert not (tmp_path / "native").exists()


def test_kernel_compiles_with_warnings_as_errors(monkeypatch, tmp_path):
    """The project's compiler builds the kernel with -Wall -Wextra -Werror (a user's newer compiler
    may fall back to a lenient build with a warning; here the strict build itself must succeed)."""
    cc = _native._compiler()
    if cc is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    assert {"-Wall", "-Wextra", "-Werror"} <= set(_native._FLAGS)
    out = _native._compile(cc, list(_native._FLAGS), _native.sources(), False)
    assert out.is_file()


def test_a_compiler_warning_falls_back_to_a_lenient_build(monkeypatch, tmp_path):
    """A strict build that fails is retried without -Werror, with a warning that says so."""
    if _native._compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("TORCH_BRDF_CACHE", str(tmp_path))
    real = _native._compile

    def strict_fails(cc, flags, files, sanitize):
        if "-Werror" in flags:
            raise OSError("cc failed (1): error: a new warning [-Werror]")
        return real(cc, flags, files, sanitize)

    monkeypatch.setattr(_native, "_compile", strict_fails)
    with pytest.warns(UserWarning, match="warnings allowed"):
        lib = _native._build()
    assert hasattr(lib, "tb_sincos")
