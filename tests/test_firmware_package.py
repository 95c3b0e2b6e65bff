"""firmware_ref/ as a drop-in for firmware projects: the CMake package, the persistence layout, the
Arduino/PlatformIO library and its example sketch.

- CMake: the library is configured and built in three configurations (double with the default
  window and all-float with W = 128 through add_subdirectory; float with W = 128 installed and found
  with find_package); a consumer (firmware_ref/cmake/consumer) links mkc::mkc, calibrates a synthetic stream and
  reports the precision and window it sees, which must be the configured ones (the capacities are
  PUBLIC compile definitions, so library and consumer agree on the state's layout). A cross build
  for Cortex-M4F runs when arm-none-eabi-gcc is here.
- Persistence: firmware_ref/tests/test_persist.c (strict warnings, as errors) checks every refusal and
  the bit-for-bit restore in C; here the bytes it saved are read independently with struct and zlib.
- Arduino: the bundle in the Arduino IDE's layout (cmake/arduino_bundle.cmake) is compiled with only
  its src/ on the include path, the example sketch against a host shim (firmware_ref/tests/arduino_shim);
  the bytes the sketch writes to Serial are decoded with the decoder `mkc-stream live --protocol binary`
  uses and must give back every sample, bit for bit, with its time; the EEPROM it wrote must be a valid
  saved calibration that a second boot restores.

Skipped, saying why, without a C compiler (CC), a C++ compiler (CXX) or cmake (Debian: apt-get
install cmake; CMake >= 3.13).
"""
from __future__ import annotations

import json
import os
import pathlib
import re
import shutil
import struct
import subprocess
import zlib

import numpy as np
import pytest

from mkc_stream.ingest.protocols import make_decoder

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
FW = REPO_ROOT / "firmware_ref"
CC = os.environ.get("CC", "cc")
CXX = os.environ.get("CXX", "c++")
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wdouble-promotion", "-Wconversion",
          "-Wshadow", "-Wstrict-prototypes", "-ffp-contract=off", "-fno-fast-math", "-O2"]
# the other library sources are the Makefile's to keep warning-free (make check, make cross): here
# only the files this test is about fail on a warning
LENIENT = [f for f in STRICT if f != "-Werror"]
PRECISION_FLAGS = {"double": [], "float": ["-DMKC_USE_FLOAT"],
                   "all-float": ["-DMKC_USE_FLOAT", "-DMKC_ACC_DOUBLE=0", "-DMKC_ESTEP_DOUBLE=0"]}

needs_cc = pytest.mark.skipif(shutil.which(CC) is None, reason=f"no C compiler: `{CC}` is not on PATH (set CC)")
needs_cxx = pytest.mark.skipif(shutil.which(CXX) is None, reason=f"no C++ compiler: `{CXX}` is not on PATH (set CXX)")
needs_cmake = pytest.mark.skipif(shutil.which("cmake") is None,
                                 reason="no cmake on PATH (Debian/Ubuntu: apt-get install cmake)")


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=kw.pop("text", True), **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n" \
                                 f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _pyproject_version() -> str:
    return re.search(r'^version = "([^"]+)"', (REPO_ROOT / "pyproject.toml").read_text(), re.M).group(1)


# ---- the persistence layout, read independently of the C code ----

def parse_saved_calibration(data: bytes) -> dict:
    """The layout of firmware_ref/include/mkc_persist.h: header, 22 reals, two int64, CRC-32."""
    assert data[:4] == b"MKCC", data[:4]
    version, real_bytes, length = struct.unpack_from("<BBH", data, 4)
    assert version == 1 and real_bytes in (4, 8)
    assert length == 22 * real_bytes + 16
    (crc,) = struct.unpack_from("<I", data, 8 + length)
    assert crc == zlib.crc32(data[:8 + length]), "CRC-32 mismatch"
    v = struct.unpack_from("<22" + ("d" if real_bytes == 8 else "f"), data, 8)
    seen, esteps = struct.unpack_from("<qq", data, 8 + 22 * real_bytes)
    return {"real_bytes": real_bytes, "size": 8 + length + 4, "b": np.array(v[0:3]),
            "S": np.array(v[3:12]).reshape(3, 3), "F": v[12], "sigma": v[13], "d": v[14],
            "quality": v[15:22], "samples_seen": seen, "esteps": esteps}


def _check_plausible(cal: dict, b_true, F_true, tol_b=0.5):
    assert np.all(np.abs(cal["b"] - np.asarray(b_true)) < tol_b), cal["b"]
    assert abs(cal["F"] - F_true) < 0.05 * F_true, cal["F"]
    S = cal["S"]
    assert np.allclose(S, S.T, atol=1e-6)
    assert abs(np.linalg.det(S) - 1.0) < 1e-3      # det S = 1 (mkc.h)
    assert cal["samples_seen"] > 0 and cal["esteps"] > 0


# ---- sources and manifests agree ----

def _makefile_list(name: str) -> list[str]:
    text = (FW / "Makefile").read_text().replace("\\\n", " ")
    return re.search(rf"^{name}\s*=(.*)$", text, re.M).group(1).split()


def test_cmake_sources_are_the_makefiles():
    text = (FW / "CMakeLists.txt").read_text()
    cm_src = re.search(r"set\(MKC_SOURCES(.*?)\)", text, re.S).group(1).split()
    cm_hdr = re.search(r"set\(MKC_PUBLIC_HEADERS(.*?)\)", text, re.S).group(1).split()
    assert sorted(cm_src) == sorted(_makefile_list("LIB_SRC"))
    assert set(_makefile_list("PUBLIC_HDR")) <= set(cm_hdr)
    assert "include/mkc_persist.h" in cm_hdr
    assert sorted(str(p.relative_to(FW)) for p in (FW / "src").glob("*.c")) == sorted(cm_src)


def test_library_manifests():
    version = _pyproject_version()
    props = dict(line.split("=", 1) for line in (FW / "library.properties").read_text().splitlines() if "=" in line)
    for key in ("name", "version", "author", "maintainer", "sentence", "paragraph", "category", "url",
                "architectures"):
        assert props.get(key), key
    assert props["version"] == version
    for header in props["includes"].split(","):
        assert (FW / "include" / header).is_file(), header
    lib = json.loads((FW / "library.json").read_text())
    assert lib["name"] == props["name"] and lib["version"] == version
    assert (FW / lib["build"]["srcDir"]).is_dir() and (FW / lib["build"]["includeDir"]).is_dir()
    assert {"target", "tests", "tools", "build"} <= set(lib["export"]["exclude"])
    for header in lib["headers"]:
        assert (FW / lib["build"]["includeDir"] / header).is_file(), header
    for ex in lib["examples"]:
        for f in ex["files"]:
            assert (FW / ex["base"] / f).is_file()


# ---- CMake ----

# (precision, window, how the consumer gets the library, expected sizeof(mkc_real), MKC_ACC_DOUBLE)
CMAKE_CONFIGS = [("double", 256, "add_subdirectory", 8, 1), ("float", 128, "find_package", 4, 1),
                 ("all-float", 128, "add_subdirectory", 4, 0)]


@needs_cc
@needs_cmake
@pytest.mark.parametrize("precision,window,how,real_bytes,acc_double", CMAKE_CONFIGS,
                         ids=[f"{c[0]}-W{c[1]}-{c[2]}" for c in CMAKE_CONFIGS])
def test_cmake_package(tmp_path, precision, window, how, real_bytes, acc_double):
    consumer = FW / "cmake" / "consumer"
    cfg = [f"-DMKC_PRECISION={precision}", f"-DMKC_W={window}"]
    if how == "add_subdirectory":
        _run(["cmake", "-S", consumer, "-B", tmp_path / "app", f"-DMKC_SOURCE_DIR={FW}", *cfg])
    else:
        _run(["cmake", "-S", FW, "-B", tmp_path / "lib", *cfg])
        _run(["cmake", "--build", tmp_path / "lib", "-j", "2"])
        _run(["cmake", "--install", tmp_path / "lib", "--prefix", tmp_path / "inst"])
        inst = tmp_path / "inst"
        assert (inst / "include" / "mkc" / "mkc_persist.h").is_file()
        config = next(inst.glob("lib*/cmake/mkc/mkcConfig.cmake"))
        assert f'set(mkc_PRECISION "{precision}")' in config.read_text()
        out = _run(["cmake", "-S", consumer, "-B", tmp_path / "app", f"-DCMAKE_PREFIX_PATH={inst}"]).stdout
        assert f"mkc {_pyproject_version()}: {precision}, W = {window}" in out
    _run(["cmake", "--build", tmp_path / "app", "-j", "2"])
    line = _run([tmp_path / "app" / "mkc_consumer"]).stdout.strip()
    got = dict(kv.split("=", 1) for kv in line.split())
    assert int(got["real_bytes"]) == real_bytes
    assert int(got["acc_double"]) == acc_double
    # the consumer's mkc.h and the library agree on the capacity: the library set the window to it
    assert int(got["capacity"]) == window == int(got["window"])
    assert got["accepted"] == "1" and got["load"] == "0" and got["same"] == "1"
    assert int(got["saved"]) == 8 + 22 * real_bytes + 16 + 4
    b = np.array([float(x) for x in got["b"].split(",")])
    assert np.all(np.abs(b - [10.0, -20.0, 5.0]) < 0.3), b


@needs_cmake
def test_cmake_rejects_unknown_precision(tmp_path):
    proc = subprocess.run(["cmake", "-S", str(FW), "-B", str(tmp_path / "b"), "-DMKC_PRECISION=half"],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    assert "MKC_PRECISION must be double, float or all-float" in proc.stderr


@needs_cmake
@pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None,
                    reason="no arm-none-eabi-gcc (Debian: gcc-arm-none-eabi, libnewlib-arm-none-eabi)")
def test_cmake_cross_cortex_m4f(tmp_path):
    _run(["cmake", "-S", FW, "-B", tmp_path, "-DCMAKE_SYSTEM_NAME=Generic", "-DCMAKE_C_COMPILER=arm-none-eabi-gcc",
          "-DCMAKE_TRY_COMPILE_TARGET_TYPE=STATIC_LIBRARY", "-DCMAKE_BUILD_TYPE=MinSizeRel",
          "-DCMAKE_C_FLAGS=-mthumb -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard", "-DMKC_PRECISION=float"])
    _run(["cmake", "--build", tmp_path, "-j", "2"])
    members = _run(["arm-none-eabi-ar", "t", tmp_path / "libmkc.a"]).stdout.split()
    assert any(m.startswith("persist.c.o") for m in members), members
    total = _run(["arm-none-eabi-size", "-t", tmp_path / "libmkc.a"]).stdout.strip().splitlines()[-1].split()
    assert int(total[0]) > 10_000 and int(total[1]) == 0 and int(total[2]) == 0   # text; no data, no bss


# ---- persistence (C test program) ----

@needs_cc
@pytest.mark.parametrize("precision", list(PRECISION_FLAGS))
def test_persist_c(tmp_path, precision):
    exe = tmp_path / "test_persist"
    flags = [*PRECISION_FLAGS[precision], "-I", FW / "include", "-I", FW / "src"]
    objs = []
    for src in [FW / "tests" / "test_persist.c", *sorted((FW / "src").glob("*.c"))]:
        objs.append(tmp_path / (src.stem + ".o"))
        strict = src.name in ("test_persist.c", "persist.c")
        _run([CC, *(STRICT if strict else LENIENT), *flags, "-c", src, "-o", objs[-1]])
    _run([CC, "-o", exe, *objs, "-lm"])
    saved = tmp_path / "saved.bin"
    out = _run([exe, saved]).stdout
    assert out.rstrip().endswith(": ok"), out
    data = saved.read_bytes()
    cal = parse_saved_calibration(data)
    assert cal["real_bytes"] == (8 if precision == "double" else 4) and len(data) == cal["size"]
    _check_plausible(cal, [12.0, -25.0, 7.5], 50.0)        # tools/synth.h: SYNTH_B, 50 uT
    printed = re.search(r"b = \[(\S+) (\S+) (\S+)\], F = (\S+):", out)
    assert np.array_equal(np.array([float(x) for x in printed.groups()[:3]], dtype=np.float32),
                          cal["b"].astype(np.float32))


# ---- Arduino: the bundle and the example sketch on a host shim ----

B_TRUE, F_TRUE = np.array([12.0, -30.0, 8.0]), 45.0
T0_US = (1 << 32) - 3_000_000      # the board's 32-bit microsecond clock wraps 3 s into the run
DT_US = 10_000                     # 100 Hz


def _samples(T=4000, seed=5) -> tuple[np.ndarray, np.ndarray]:
    """Pole-to-pole spiral of a 45 uT field through soft and hard iron, 0.3 uT noise; float32 uT."""
    k = np.arange(T)
    s = (k % 2000) / 2000
    z = np.cos(2 * np.pi * s)
    phi = 2 * np.pi * 17 * s
    r = np.sqrt(1 - z * z)
    u = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    S_inv = np.array([[1.1, 0.05, 0.0], [0.05, 0.9, 0.02], [0.0, 0.02, 1.0]])
    m = (F_TRUE * u) @ S_inv.T + B_TRUE + 0.3 * np.random.default_rng(seed).standard_normal((T, 3))
    return (T0_US + k * DT_US).astype(np.int64), m.astype(np.float32)


@pytest.fixture(scope="module")
def sketch(tmp_path_factory):
    """The Arduino bundle and the sketch built against it and the shim: {mode: executable}."""
    if shutil.which(CC) is None or shutil.which(CXX) is None or shutil.which("cmake") is None:
        pytest.skip(f"needs {CC}, {CXX} and cmake (Debian: apt-get install cmake)")
    d = tmp_path_factory.mktemp("arduino")
    _run(["cmake", f"-DOUT={d}", "-P", FW / "cmake" / "arduino_bundle.cmake"])
    lib = d / "mkc"
    assert (d / "mkc.zip").is_file() and (lib / "library.properties").is_file()
    shim = FW / "tests" / "arduino_shim"
    objs = []
    for src in sorted((lib / "src").glob("*.c")):   # Arduino's include path: the library's src/ only
        obj = d / (src.stem + ".o")
        _run([CC, *(STRICT if src.name == "persist.c" else LENIENT), "-I", lib / "src", "-c", src, "-o", obj])
        objs.append(obj)
    cxx = ["-std=c++11", "-O1", "-Wall", "-Wextra", "-Werror", "-I", shim, "-I", lib / "src"]
    _run([CXX, *cxx, "-c", shim / "shim_main.cpp", "-o", d / "shim.o"])
    exes = {}
    for mode, text in (("frames", 0), ("text", 1)):
        _run([CXX, *cxx, f"-DTEXT_REPORT={text}", "-x", "c++", "-c",
              lib / "examples" / "live_calibration" / "live_calibration.ino", "-o", d / f"sketch_{mode}.o"])
        exes[mode] = d / f"sketch_{mode}"
        _run([CXX, "-o", exes[mode], d / f"sketch_{mode}.o", d / "shim.o", *objs, "-lm"])
    t_us, mags = _samples()
    with open(d / "samples.csv", "w") as fh:
        for t, (x, y, z) in zip(t_us, mags):
            fh.write(f"{t},{float(x):.9g},{float(y):.9g},{float(z):.9g}\n")   # 9 digits: float32 exactly
    return {"dir": d, "exe": exes, "t_us": t_us, "mags": mags}


def _boot(sk, mode, eeprom) -> tuple[bytes, str]:
    env = dict(os.environ, MKC_SHIM_SAMPLES=str(sk["dir"] / "samples.csv"), MKC_SHIM_EEPROM=str(eeprom))
    proc = _run([sk["exe"][mode]], env=env, text=False)
    return proc.stdout, proc.stderr.decode()


def test_sketch_speaks_the_binary_protocol(sketch, tmp_path):
    eeprom = tmp_path / "eeprom.bin"                       # absent: an erased EEPROM
    out, err = _boot(sketch, "frames", eeprom)
    assert f"samples {len(sketch['mags'])}" in err
    banner = b"no calibration restored: no saved calibration (magic)\n"
    assert out.startswith(banner)
    dec = make_decoder("binary")                           # what `mkc-stream live --protocol binary` uses
    got = dec.feed(out) + dec.flush()
    c = dec.counts
    assert c.frames == len(got) == len(sketch["mags"])
    assert c.bad_frames == 0 and c.drops == 0 and c.skipped_bytes == 0 and dec.crc_errors == 0
    assert c.lead_in_bytes == len(banner)
    assert [s.seq for s in got] == [k & 0xFFFF for k in range(len(got))]
    mags = np.array([s.mag for s in got])
    assert np.array_equal(mags.astype(np.float32), sketch["mags"])      # bit for bit
    assert np.array_equal(mags, sketch["mags"].astype(np.float64))
    # device time: the 32-bit microsecond clock, unwrapped across its wrap by the decoder
    t = np.array([s.t for s in got])
    assert np.allclose(t, sketch["t_us"] * 1e-6, rtol=0, atol=1e-9)
    assert t[-1] > 2.0 ** 32 * 1e-6

    # the sketch saved its accepted calibration: a valid layout, a plausible calibration
    cal = parse_saved_calibration(eeprom.read_bytes())
    _check_plausible(cal, B_TRUE, F_TRUE)
    assert cal["real_bytes"] == 8                          # the library's default build (double)


def test_sketch_restores_after_reset(sketch, tmp_path):
    eeprom = tmp_path / "eeprom.bin"
    _boot(sketch, "frames", eeprom)
    saved = eeprom.read_bytes()
    cal = parse_saved_calibration(saved)

    # the next boot restores it and says so, in text mode; then it reports and applies calibrations
    text, _ = _boot(sketch, "text", eeprom)
    text = text.decode()
    m = re.search(r"^restored from EEPROM: b = \[(\S+), (\S+), (\S+)\] uT, F = (\S+) uT", text, re.M)
    assert m, text[:500]
    assert np.allclose([float(x) for x in m.groups()[:3]], cal["b"], rtol=0, atol=1e-6)
    assert abs(float(m.group(4)) - cal["F"]) < 1e-6
    # calibrated from the first sample on (the restored calibration): |m| close to the field
    corrected = np.array([[float(x) for x in line.split()[1:4]]
                          for line in re.findall(r"^corrected: .*$", text, re.M)])
    assert len(corrected) == len(sketch["mags"]) // 50
    assert np.all(np.abs(np.linalg.norm(corrected, axis=1) / cal["F"] - 1) < 0.05)

    # damaged EEPROM: refused with its reason, the board calibrates from scratch
    bad = bytearray(saved)
    bad[40] ^= 0x10
    eeprom.write_bytes(bytes(bad))
    text, _ = _boot(sketch, "text", eeprom)
    text = text.decode()
    assert text.startswith("no calibration restored: damaged (CRC mismatch)\n")
    assert re.search(r"^accepted: b = ", text, re.M) and re.search(r"^saved to EEPROM: \d+ bytes$", text, re.M)
    parse_saved_calibration(eeprom.read_bytes())           # rewritten, valid again


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pty (POSIX)")
def test_mkc_stream_live_watches_the_sketch(sketch, tmp_path, capsys):
    """The sketch's Serial bytes through a pty into `mkc-stream live --protocol binary`: every sample
    recorded as sent, and the host calibrates them."""
    import termios
    import threading
    import time
    import tty

    from mkc_stream.cli import main
    from mkc_stream.io.recording import read_recording

    out, _ = _boot(sketch, "frames", tmp_path / "eeprom.bin")
    master, slave = os.openpty()
    tty.setraw(slave)                                    # a byte pipe, like a UART

    def board():
        # pyserial empties the port's input when it opens it (a board's bytes from before are not
        # read): start sending once live has set the port's baud rate, as a board reset then would
        deadline = time.monotonic() + 60
        while termios.tcgetattr(slave)[4] != termios.B115200 and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)
        view = memoryview(out)
        while view:
            view = view[os.write(master, view[:4096]):]

    writer = threading.Thread(target=board, daemon=True)
    try:
        writer.start()
        n = len(sketch["mags"])
        code = main(["live", "--port", os.ttyname(slave), "--protocol", "binary", "--max-samples", str(n),
                     "--out", str(tmp_path / "board.csv"), "--json", "-", "--quiet"])
        writer.join(timeout=30)
    finally:
        os.close(slave)
        os.close(master)
    obj = json.loads(capsys.readouterr().out)
    assert obj["ended"] == "max samples"
    c = obj["counts"]
    assert c["samples"] == n and c["bad_frames"] == 0 and c["drops"] == 0
    assert code == 0 and obj["status"] == "accepted", obj.get("reason")
    assert np.allclose(obj["hard_iron"], B_TRUE, atol=0.5)
    rec = read_recording(tmp_path / "board.csv")
    assert len(rec) == n
    assert np.array_equal(np.asarray(rec.mag, dtype=np.float32), sketch["mags"])
