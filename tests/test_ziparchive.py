"""The one zip validator (gsa.ziparchive), as the library uses it: every defect in
tests/zip_defects.py is an ImageSetError with a one-line message (never zipfile's own
exceptions), a good archive still loads, and `gsa align lie.zip t.ply` prints one
`gsa: error:` line and exits 1 (it printed a 29-line traceback)."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from gsa.recon.images import ImageSetError, check_zip, load_image_set
from gsa.ziparchive import ZipArchiveError, ZipLimits, unsafe_member_name
from gsa.ziparchive import check_zip as shared_check_zip
from tests.zip_defects import build, cases, good, png

ROOT = Path(__file__).resolve().parents[1]
CASES = cases()


@pytest.mark.parametrize("defect", list(CASES))
def test_every_defect_is_one_clear_error(tmp_path, defect):
    p = tmp_path / f"{defect}.zip"
    p.write_bytes(CASES[defect])
    with pytest.raises(ImageSetError) as e:
        check_zip(p)
    msg = str(e.value)
    assert msg.startswith(f"{defect}.zip: ") and "\n" not in msg, msg
    with pytest.raises(ImageSetError):  # and so is loading it as an image set
        load_image_set(p)


@pytest.mark.parametrize("method", [zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
def test_good_archives_pass_and_load(tmp_path, method):
    p = tmp_path / "ok.zip"
    p.write_bytes(good(4, method))
    assert [i.filename for i in check_zip(p)] == [f"v{i}.png" for i in range(4)]
    s = load_image_set(p)
    assert len(s) == 4 and (s.width, s.height) == (32, 24)


def test_lies_about_sizes_are_named(tmp_path):
    p = tmp_path / "lie.zip"
    p.write_bytes(CASES["size-larger-than-data"])
    with pytest.raises(ZipArchiveError, match=r"entry 'v0.png' declares \d+ bytes but holds \d+") as e:
        shared_check_zip(p)
    assert not e.value.limit
    p.write_bytes(CASES["header-name-differs"])
    with pytest.raises(ZipArchiveError, match="File name in directory 'v0.png' and header"):
        shared_check_zip(p)


class _Stream:
    """A write-only stream: zipfile then writes each entry's CRC and sizes in a data descriptor
    after its data (flag bit 3), with zeros in its local header, as streaming zip tools do."""

    def __init__(self):
        self.data = bytearray()

    def write(self, b):
        self.data += b
        return len(b)

    def flush(self):
        pass


def test_local_headers_are_held_to_the_directory(tmp_path):
    """zipfile reads by the central directory and never compares a local header's sizes or CRC
    with it; other readers go by the local header, so an archive whose two disagree is refused,
    naming the field. Local headers that agree in another form still pass: zip64 sizes in the
    extra field, zeros with a data descriptor after the data."""
    p = tmp_path / "z.zip"
    for defect, what in [
        ("local-size-differs", "size"),
        ("local-compressed-size-differs", "compressed size"),
        ("local-crc-differs", "CRC-32"),
        ("local-method-differs", "compression method"),
    ]:
        p.write_bytes(CASES[defect])
        with pytest.raises(ZipArchiveError, match=f"its local header says {what} \\d+, the central directory \\d+"):
            shared_check_zip(p)
    import io

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for i in range(3):
            with z.open(f"v{i}.png", "w", force_zip64=True) as fh:  # as the service stores image sets
                fh.write(png(seed=i))
    p.write_bytes(buf.getvalue())
    assert len(shared_check_zip(p)) == 3
    stream = _Stream()
    with zipfile.ZipFile(stream, "w", zipfile.ZIP_DEFLATED) as z:
        for i in range(3):
            z.writestr(f"v{i}.png", png(seed=i))
    data = bytes(stream.data)
    assert data[6] & 0x8  # the local header defers to a data descriptor
    p.write_bytes(data)
    assert len(shared_check_zip(p)) == 3
    at = data.index(b"PK\x07\x08")  # the first entry's descriptor: a size that is not the directory's
    p.write_bytes(data[: at + 12] + (123).to_bytes(4, "little") + data[at + 16 :])
    with pytest.raises(ZipArchiveError, match="its data descriptor does not say what the central directory says"):
        shared_check_zip(p)


def test_limits_are_flagged_as_limits(tmp_path):
    p = tmp_path / "z.zip"
    p.write_bytes(build({f"v{i}.png": png(seed=i) for i in range(4)}))
    with pytest.raises(ZipArchiveError, match="4 entries exceeds the limit of 3") as e:
        shared_check_zip(p, ZipLimits(max_entries=3))
    assert e.value.limit
    with pytest.raises(ZipArchiveError, match="uncompressed size exceeds") as e:
        shared_check_zip(p, ZipLimits(max_bytes=1000))
    assert e.value.limit


def test_ratio_checks_start_at_1_kib(tmp_path):
    # the strictest of the two old rules: the service held entries over 1 KiB to the ratio,
    # the library only those over 1 MiB
    p = tmp_path / "z.zip"
    p.write_bytes(build({"v0.png": b"\0" * 300_000}))
    with pytest.raises(ZipArchiveError, match="suspicious compression ratio"):
        shared_check_zip(p)
    p.write_bytes(build({"small.txt": b"\0" * 1024}))  # at the floor: not held to the ratio
    assert len(shared_check_zip(p)) == 1


@pytest.mark.parametrize(
    "name", ["../etc/passwd", "a/../../b", "/abs", "C:\\x", "C:x", "a\\b", "", "a\x00b", "\\\\server\\share"]
)
def test_unsafe_names(name):
    assert unsafe_member_name(name)


@pytest.mark.parametrize("name", ["views/0001.png", "a..b.png", "x/.hidden.png", "__MACOSX/._v0.png"])
def test_safe_names(name):
    assert unsafe_member_name(name) is None


def test_the_service_uses_the_same_validator():
    import service.jobs.inputs

    assert service.jobs.inputs.check_zip is shared_check_zip
    assert service.jobs.inputs.unsafe_member_name is unsafe_member_name


@pytest.mark.slow
def test_gsa_align_on_a_lying_zip_is_one_line(tmp_path, car_model):
    from gsa.io.ply import write_ply

    lie = tmp_path / "lie.zip"
    lie.write_bytes(CASES["size-smaller-than-data"])
    target = tmp_path / "t.ply"
    write_ply(car_model, target)
    r = subprocess.run(
        [sys.executable, "-m", "gsa.cli", "align", str(lie), str(target), "--out", str(tmp_path / "r.json")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1, r
    assert "Traceback" not in r.stderr, r.stderr
    errors = [line for line in r.stderr.splitlines() if "error" in line]
    assert errors == [
        "gsa: error: lie.zip: entry 'v0.png' is corrupt or does not hold what the archive declares "
        "(Bad CRC-32 for file 'v0.png')"
    ], r.stderr
