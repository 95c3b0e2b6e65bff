"""Write the malformed-recording corpus tests/malformed/ (run once; the files are committed).

    python firmware_ref/tests/make_malformed.py

Each file is one kind of hostile input to the recording reader: truncations, byte flips, NUL
bytes, line ends and BOMs, repeated/missing/empty columns, Python float syntax, huge and
non-finite values, Unicode digits and spaces, invalid UTF-8, metadata conflicts, lines at and over
the 64 KiB preamble limit. tests/test_hostile_c.py checks that mkc_replay's reader and
mkc_stream.io.recording.read_recording agree on every one (samples kept, bad rows by line and
kind, or both refuse); `make -C firmware_ref sanitize` replays them all under ASan/UBSan.
Inputs of many megabytes are generated at test time instead (tests/test_hostile_c.py, Makefile).
"""
from __future__ import annotations

import pathlib
import random

OUT = pathlib.Path(__file__).resolve().parent / "malformed"

# a small valid recording: a slow rotation, exact decimal text
ROWS = [f"{i * 0.02:.2f},{30 + (i * 7) % 23 - 11.5:.3f},{-12 + (i * 5) % 19:.3f},{40 - (i * 3) % 17:.3f},"
        f"{(i % 5) * 0.25:.2f}" for i in range(24)]
VALID = "# units.mag: uT\n# sensor: corpus\nt,mx,my,mz,temp\n" + "\n".join(ROWS) + "\n"
V = VALID.encode()
BODY = "\n".join(ROWS) + "\n"
H = "t,mx,my,mz\n"


def rows4(cells: list[str]) -> str:
    """one row per value: t increasing, the value in mx"""
    return H + "".join(f"{0.1 * k:.1f},{c},2,3\n" for k, c in enumerate(cells))


def cases() -> dict[str, bytes]:
    c: dict[str, bytes] = {}
    c["valid.csv"] = V
    # empty and near-empty
    c["empty.csv"] = b""
    c["blank_only.csv"] = b"\n  \n\t\n"
    c["header_only.csv"] = b"t,mx,my,mz\n"
    c["header_only_no_newline.csv"] = b"t,mx,my,mz"
    c["meta_only.csv"] = b"# units.mag: uT\n# sensor: x\n"
    c["hash_only.csv"] = b"#\n#\n"
    # truncations
    n = len(V)
    c["cut_mid_number.csv"] = V[:n - 3]
    c["cut_mid_row.csv"] = V[:V.rindex(b",", 0, n - 1) - 2]
    c["cut_after_comma.csv"] = V[:V.rindex(b",", 0, n - 1) + 1]
    c["cut_in_header.csv"] = V[:V.index(b"t,mx") + 6]
    c["cut_in_meta.csv"] = V[:10]
    rng = random.Random(26)
    for k in range(6):
        c[f"cut_random_{k}.csv"] = V[:rng.randrange(n)]
    # byte flips
    for k in range(8):
        b = bytearray(V)
        for _ in range(1 + k % 3):
            b[rng.randrange(n)] = rng.randrange(256)
        c[f"flip_random_{k}.csv"] = bytes(b)
    # NUL bytes
    mid = V.index(b"\n", n // 2)
    c["nul_in_row.csv"] = V[:mid - 2] + b"\0" + V[mid - 2:]
    c["nul_row.csv"] = V[:mid + 1] + b"\0\n" + V[mid + 1:]
    c["nul_at_end.csv"] = V + b"\0"
    c["nul_in_header.csv"] = V.replace(b"t,mx", b"t\0,mx")
    c["nul_in_meta.csv"] = V.replace(b"# sensor", b"# sen\0sor")
    # line ends and byte order marks
    c["crlf.csv"] = V.replace(b"\n", b"\r\n")
    c["cr_only.csv"] = V.replace(b"\n", b"\r")
    c["mixed_eol.csv"] = V.replace(b"\n", b"\r\n", 5).replace(b"0.10,", b"\r0.10,")
    c["bom.csv"] = b"\xef\xbb\xbf" + V
    c["bom_crlf.csv"] = b"\xef\xbb\xbf" + V.replace(b"\n", b"\r\n")
    c["bom_twice.csv"] = b"\xef\xbb\xbf\xef\xbb\xbf" + H.encode() + BODY.encode()
    c["bom_before_header.csv"] = b"# a: b\n\xef\xbb\xbf" + H.encode() + b"0,1,2,3\n"
    c["utf16le.csv"] = b"\xff\xfe" + VALID.encode("utf-16-le")
    c["utf16be.csv"] = b"\xfe\xff" + VALID.encode("utf-16-be")
    # columns
    c["dup_column.csv"] = ("t,mx,my,mz,mx\n" + "".join(f"{r},1\n" for r in ROWS)).encode()
    c["dup_column_spaces.csv"] = ("t, mx ,my,mz,mx \n0,1,2,3,4\n").encode()
    c["dup_required.csv"] = b"t,t,mx,my,mz\n0,0,1,2,3\n"
    c["dup_many.csv"] = b"t,mx,my,mz,a,b,a,b,c,c,d,d,e,e,f,f\n"
    c["dup_invalid_utf8.csv"] = b"t,mx,my,mz,\xff,\xfe\n0,1,2,3,4,5\n"
    c["missing_column.csv"] = b"t,mx,my\n0,1,2\n"
    c["case_columns.csv"] = b"T,MX,MY,MZ\n0,1,2,3\n"
    c["empty_column_name.csv"] = b"t,mx,,my,mz\n0,1,2,3,4\n"
    c["trailing_comma_header.csv"] = b"t,mx,my,mz,\n0,1,2,3,\n"
    c["semicolons.csv"] = b"t;mx;my;mz\n0;1;2;3\n"
    c["tabs.csv"] = b"t\tmx\tmy\tmz\n0\t1\t2\t3\n"
    c["header_spaces.csv"] = (" t , mx ,my,\tmz , temp\n" + "".join(f" {r} \n" for r in ROWS)).encode()
    c["wide_300_columns.csv"] = (H[:-1] + "".join(f",c{k}" for k in range(300)) + "\n" +
                                 "".join(f"{k},1,2,3" + ",0.5" * 300 + "\n" for k in range(5))).encode()
    c["cell_counts.csv"] = (H + "0,1,2,3\n0.1,1,2\n0.2,1,2,3,4\n0.3,,,,\n0.4\n,\n0.5,1,2,3\n").encode()
    # values
    c["huge_values.csv"] = rows4(["1e300", "-1.7976931348623157e308", "1e-300", "123456789012345678901234567890"]).encode()
    c["overflow.csv"] = rows4(["1e309", "-1e309", "1" + "0" * 400, "0." + "0" * 400 + "1"]).encode()
    c["nonfinite.csv"] = (H + "0,inf,2,3\n0.1,1,-inf,3\n0.2,1,2,nan\ninf,1,2,3\nnan,1,2,3\n0.3,Infinity,2,3\n"
                          "0.4,NaN,2,3\n0.5,1,2,-Infinity\n0.6,1,2,3\n").encode()
    c["nonfinite_aux.csv"] = b"t,mx,my,mz,aux\n0,1,2,3,inf\n0.1,1,2,3,nan\n0.2,1,2,3,\n0.3,1,2,3,x\n"
    c["subnormal.csv"] = rows4(["4.9e-324", "2.4703282292062328e-324", "2.4703282292062327e-324", "5e-325",
                                "2.2250738585072011e-308"]).encode()
    c["underscores.csv"] = rows4(["1_000", "1__0", "_1", "1_", "1_.5", "1._5", "1e1_0", "1_e5", "0_0.0_1"]).encode()
    c["float_syntax.csv"] = rows4([".5", "5.", "+1", "-0", "1E5", "1e", "e5", "0x10", "1d5", " 1 ", "1 2", "infinit",
                                   "nan(1)", "+nan", "-Infinity", "iNf", "+.e1", ".", "-", "++1", "1e+", "1e-5",
                                   "00012", "1.5e0003", "0e99999999999"]).encode()
    c["unicode_digits.csv"] = rows4(["\u0661\u0662", "\uff11\uff12.\uff15", "\u0967e\u0968", "\U0001d7ce",
                                     "\u00b2", "\u2155", "1\u0663"]).encode()
    c["unicode_space.csv"] = (H + "0,\u00a01\u00a0,2,3\n\u3000\n0.1, \u20281,2,3\n\x1c\n0.2,\x1c1\x1f,2,3\n"
                              "0.3,1\u20092,2,3\n\u0085\n0.4,\ufeff1,2,3\n0.5,1,2,3\x1e\n").encode()
    c["invalid_utf8.csv"] = (H.encode() + b"0,1,2,3\n0.1,\xff,2,3\n0.2,1,2,3\xc3\n0.3,\xc0\xb1,2,3\n"
                             b"0.4,\xed\xa0\x80,2,3\n0.5,\xe2\x80,2,3\n0.6,1,2,3\n")
    c["long_number.csv"] = (H + "0,1,2,3\n0.1," + "7" * 100_000 + ",2,3\n0.2,0." + "0" * 50_000 + "3,2,3\n").encode()
    c["t_decreasing.csv"] = (H + "0,1,2,3\n0.2,1,2,3\n0.1,1,2,3\n0.2,1,2,3\n-0,1,2,3\n0.3,1,2,3\n").encode()
    c["t_nan_rows.csv"] = (H + "0,1,2,3\n,1,2,3\nnan,1,2,3\n1,1,2,3\n0.5,1,2,3\n1,1,2,3\n").encode()
    c["comments_in_body.csv"] = (H + "0,1,2,3\n# later comment\n  # indented\n0.1,1,2,3\n#\n").encode()
    c["blank_lines.csv"] = (H + "\n\n0,1,2,3\n   \n\t\n0.1,1,2,3\n\n\n").encode()
    c["last_line_spaces.csv"] = (H + "0,1,2,3\n0.1,1,2,x\n   ").encode()
    c["last_line_ok_no_newline.csv"] = (H + "0,1,2,3\n0.1,1,2,3").encode()
    c["last_line_bad_no_newline.csv"] = (H + "0,1,2,3\n0.1,1,2").encode()
    c["long_body_line.csv"] = (H + "0,1,2,3\n" + "x" * 100_000 + "\n0.1,1,2,3\n" + "," * 50_000 + "\n").encode()
    # metadata
    c["meta_conflict.csv"] = b"# units.mag: uT\n# units.mag: counts\n" + H.encode() + b"0,1,2,3\n"
    c["meta_same_twice.csv"] = b"# units.mag: uT\n#units.mag:uT  \n" + H.encode() + b"0,1,2,3\n"
    c["meta_free_text.csv"] = b"# just a note\n# another: with colon\n#: empty key\n" + H.encode() + b"0,1,2,3\n"
    c["meta_comment_key.csv"] = b"# comment: a\n# comment: a\n" + H.encode() + b"0,1,2,3\n"
    c["meta_comment_twice.csv"] = b"# comment: a\n# comment: b\n" + H.encode() + b"0,1,2,3\n"
    c["meta_text_then_comment_key.csv"] = b"# a note\n# comment: a note\n" + H.encode() + b"0,1,2,3\n"
    c["meta_text_then_comment_other.csv"] = b"# a note\n# comment: x\n" + H.encode() + b"0,1,2,3\n"
    c["meta_invalid_utf8_keys.csv"] = b"# \xff: 1\n# \xfe: 2\n" + H.encode() + b"0,1,2,3\n"
    c["meta_unit_odd.csv"] = b"# units.mag: \xc2\xb5T\n" + H.encode() + b"0,1,2,3\n"
    # the 64 KiB limit of metadata and header lines (bytes, then characters)
    c["meta_line_at_limit.csv"] = b"# pad: " + b"p" * (65536 - 7) + b"\n" + H.encode() + b"0,1,2,3\n"
    c["meta_line_over_limit.csv"] = b"# pad: " + b"p" * (65536 - 6) + b"\n" + H.encode() + b"0,1,2,3\n"
    c["meta_line_limit_crlf.csv"] = b"# pad: " + b"p" * (65536 - 7) + b"\r\n" + H.encode() + b"0,1,2,3\n"
    c["header_over_limit.csv"] = (H[:-1] + "".join(f",c{k}" for k in range(12_000)) + "\n0,1,2,3\n").encode()
    c["blank_line_over_limit.csv"] = b" " * 70_000 + b"\n" + H.encode() + b"0,1,2,3\n"
    return c


def main() -> None:
    OUT.mkdir(exist_ok=True)
    for old in OUT.iterdir():
        old.unlink()
    for name, data in cases().items():
        (OUT / name).write_bytes(data)
    print(f"{len(cases())} files in {OUT}")


if __name__ == "__main__":
    main()
