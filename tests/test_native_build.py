"""Building bundled C kernels at first use: cache, keys, and clear reasons when not."""

from __future__ import annotations

import platform
import shutil

import pytest
import torch

from core.kernels import native_build
from core.render.raster import cpu_simd, rasterize
from tests.test_raster_cpu import _camera, _scene

GOOD = "int answer(int x) { return 2 * x + 1; }\n"

needs_cc = pytest.mark.skipif(native_build._compiler() is None, reason="no C compiler here")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GLINT_NATIVE_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("GLINT_NATIVE", raising=False)
    return tmp_path / "cache"


def _source(tmp_path, name: str, text: str):
    path = tmp_path / f"{name}.c"
    path.write_text(text)
    return path


@needs_cc
def test_builds_once_and_reuses_the_cached_library(tmp_path, cache, monkeypatch):
    src = _source(tmp_path, "good", GOOD)
    lib = native_build.load(src)
    assert lib is not None and lib.answer(20) == 41
    built = list(cache.glob("good-*.so"))
    assert len(built) == 1
    # A new process (no in-memory memo) loads the cached file without compiling.
    monkeypatch.setattr(native_build, "_compile", lambda *a: pytest.fail("recompiled"))
    lib2, why = native_build._build_and_load(src, ())
    assert lib2 is not None and why == "" and lib2.answer(1) == 3


@needs_cc
def test_cache_key_covers_source_and_cpu(tmp_path, cache, monkeypatch):
    src = _source(tmp_path, "keyed", GOOD)
    assert native_build._build_and_load(src, ())[0] is not None
    monkeypatch.setattr(native_build, "_cpu_signature", lambda: "another machine")
    assert native_build._build_and_load(src, ())[0] is not None
    src.write_text(GOOD + "int other(void) { return 7; }\n")
    lib, _ = native_build._build_and_load(src, ())
    assert lib.other() == 7
    assert len(list(cache.glob("keyed-*.so"))) == 3


@needs_cc
def test_compile_error_is_reported_and_remembered(tmp_path, cache):
    src = _source(tmp_path, "broken", "int f(void) { return nope; }\n")
    assert native_build.load(src) is None
    why = native_build.why_unavailable(src)
    assert "broken.c" in why and "nope" in why and "exited" in why
    assert not list(cache.glob("*.so")) and not list(cache.glob("*.tmp*"))


def test_missing_compiler_gives_a_reason(tmp_path, cache, monkeypatch):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    src = _source(tmp_path, "nocc", GOOD)
    assert native_build.load(src) is None
    assert "no C compiler found" in native_build.why_unavailable(src)


def test_missing_source_gives_a_reason(tmp_path, cache):
    src = tmp_path / "absent.c"
    assert native_build.load(src) is None
    assert "missing from the installation" in native_build.why_unavailable(src)


@needs_cc
def test_unwritable_cache_gives_a_reason(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("GLINT_NATIVE_CACHE", str(blocker / "cache"))
    src = _source(tmp_path, "nocache", GOOD)
    assert native_build.load(src) is None
    assert "cannot write" in native_build.why_unavailable(src)


def test_switched_off_falls_back_to_numba(monkeypatch):
    monkeypatch.setenv("GLINT_NATIVE", "0")
    assert cpu_simd.library() is None
    assert "GLINT_NATIVE=0" in cpu_simd.why_unavailable()
    cam = _camera(30, 20)
    scene = _scene(60, 1, 3, torch.float32)
    with torch.no_grad():
        off = rasterize(*scene, cam, backend="cpu")
    monkeypatch.delenv("GLINT_NATIVE")
    with torch.no_grad():
        ref = rasterize(*scene, cam, backend="reference")
    torch.testing.assert_close(off.features, ref.features, rtol=1e-5, atol=1e-5)


def test_service_settings_reach_the_kernel_loader(monkeypatch, tmp_path):
    """``Settings.native*`` (also from a .env file) replace the environment's values."""
    from api.service.settings import Settings, apply_to_core

    monkeypatch.delenv("GLINT_NATIVE", raising=False)
    monkeypatch.delenv("GLINT_NATIVE_CACHE", raising=False)
    try:
        apply_to_core(Settings(native=False, native_cache=tmp_path / "kc"))
        assert cpu_simd.library() is None
        assert "GLINT_NATIVE=0" in cpu_simd.why_unavailable()
        assert native_build.cache_dir() == tmp_path / "kc"
    finally:
        native_build.configure()
    assert native_build.cache_dir() != tmp_path / "kc"
    assert cpu_simd.why_unavailable() is None or "GLINT_NATIVE=0" not in cpu_simd.why_unavailable()


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv("GLINT_NATIVE_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert native_build.cache_dir() == tmp_path / "glint" / "native"


def test_compiler_choice_honours_cc(monkeypatch):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler here")
    monkeypatch.setenv("CC", cc)
    assert native_build._compiler() == cc


@needs_cc
def test_prebuilt_variants_load_without_a_compiler(tmp_path, cache, monkeypatch):
    if not native_build._levels():
        pytest.skip(f"no prebuilt levels for {platform.machine()}")
    src = _source(tmp_path, "pre", GOOD)
    out = tmp_path / "prebuilt"
    built = native_build.prebuild(out, (src,))
    levels = [lv for lv, _ in native_build._levels()]
    assert [p.name for p in built] == [native_build._prebuilt_name(src, lv) for lv in levels]
    assert all(p.is_file() for p in built) and not list(cache.glob("*"))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setenv("GLINT_NATIVE_PREBUILT", str(out))
    lib, why = native_build._build_and_load(src, ())
    assert lib is not None and lib.answer(3) == 7
    best = next(lv for lv, needs in native_build._levels() if needs <= native_build._cpu_flags())
    assert lib._name.endswith(f"-{best}.so")
    # A CPU without any of the optional flags gets the baseline build.
    monkeypatch.setattr(native_build, "_cpu_flags", frozenset)
    lib, _ = native_build._build_and_load(src, ())
    assert lib._name.endswith(f"-{native_build._levels()[-1][0]}.so")
    # An edited source does not pick up a stale prebuilt library.
    src.write_text(GOOD + "int other(void) { return 7; }\n")
    lib, why = native_build._build_and_load(src, ())
    assert lib is None and "no C compiler found" in why


def test_prebuild_needs_a_compiler(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    with pytest.raises(RuntimeError, match="no C compiler found"):
        native_build.prebuild(tmp_path / "out")


def test_glint_info_says_which_compositing_kernel_runs(monkeypatch, capsys):
    import json

    from core.cli import main

    monkeypatch.setenv("GLINT_NATIVE", "0")
    assert main(["info"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cpu_compositing"] == {
        "kernel": "numba",
        "why": "GLINT_NATIVE=0 turns native kernels off",
    }
    monkeypatch.delenv("GLINT_NATIVE")
    if cpu_simd.why_unavailable() is None:
        assert main(["info"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert info["cpu_compositing"]["kernel"] == "simd"
        assert info["cpu_compositing"]["library"].endswith(".so")
