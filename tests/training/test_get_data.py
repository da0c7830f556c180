"""`python -m training.data.get` and its catalogue, offline: a file:// mirror laid out like raw.githubusercontent.com.

The mirror holds a sample of the byte-identical files of every source, taken from the data directory
($WEARMOCAP_DATA_DIR); the two converters are checked on small inputs in their original formats, written here, against
hand-computed output.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import math
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from training.data import li2018_bvh, xsens_mt
from training.data.build_catalogue import catalogue_entry
from training.data.download import index_of_present_files
from training.data.get import main
from training.data.origins import (
    FileEntry,
    carried_file,
    load_catalogue,
    read_files_table,
    write_files_table,
)

REPO = Path(__file__).resolve().parents[2]
CATALOGUE = load_catalogue()
RAW = CATALOGUE.raw_base + "/"


@pytest.fixture(scope="module")
def data_root(data_dir: Path) -> Path:
    """The data directory (tests/conftest.py: skipped with the reason when WEARMOCAP_DATA_DIR is unset)."""
    return data_dir


@pytest.fixture(scope="module")
def table() -> list[FileEntry]:
    return read_files_table()


def index_paths(data_root: Path) -> set[str]:
    with open(data_root / "index.csv", newline="") as fh:
        return {row["path"] for row in csv.DictReader(fh)}


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def content(path: Path) -> bytes:
    """A file's bytes, gunzipped for ``.gz``."""
    data = path.read_bytes()
    return gzip.decompress(data) if path.suffix == ".gz" else data


def mirror_path(mirror: Path, url: str) -> Path:
    assert url.startswith(RAW), url
    return mirror / unquote(url[len(RAW) :])


def sample(table: list[FileEntry], indexed: set[str]) -> list[FileEntry]:
    """Per source the smallest copied data file, kept file (licence, README, JSON) and gzipped file; carried files."""
    kinds = (
        lambda e: e.transform == "copy" and e.path in indexed,
        lambda e: e.transform == "copy" and e.path not in indexed,
        lambda e: e.transform == "gzip",
    )
    chosen = [e for e in table if e.transform == "carried"]
    for source in CATALOGUE.sources:
        for kind in kinds:
            chosen += sorted((e for e in table if e.source == source and kind(e)), key=lambda e: e.bytes)[:1]
    return chosen


def build_mirror(mirror: Path, entries: list[FileEntry], data_root: Path) -> None:
    """Origin files as the origin serves them: byte-identical copies, gzipped ones unpacked."""
    for e in entries:
        if e.url:
            target = mirror_path(mirror, e.url)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(content(data_root / e.path))


def run_get(*args: str | Path) -> tuple[int, str]:
    proc = subprocess.run(
        [sys.executable, "-m", "training.data.get", *map(str, args)], cwd=REPO, capture_output=True, text=True
    )
    return proc.returncode, proc.stdout + proc.stderr


@pytest.fixture()
def sampled(tmp_path: Path, data_root: Path, table: list[FileEntry]) -> tuple[list[FileEntry], Path, Path]:
    entries = sample(table, index_paths(data_root))
    mirror, sample_table = tmp_path / "mirror", tmp_path / "files.csv.gz"
    build_mirror(mirror, entries, data_root)
    write_files_table(entries, sample_table)
    return entries, mirror, sample_table


# ---- the catalogue ----


def test_catalogue_lists_every_file_of_the_data_directory(data_root: Path, table: list[FileEntry]) -> None:
    on_disk = {p.relative_to(data_root).as_posix(): p.stat().st_size for p in data_root.rglob("*") if p.is_file()}
    assert {e.path: e.bytes for e in table} == on_disk, "stale: python -m training.data.build_catalogue --data-dir"
    with open(data_root / "index.csv", newline="") as fh:
        index_sources = {row["path"]: row["source"] for row in csv.DictReader(fh)}
    assert {e.path: e.source for e in table if e.path in index_sources} == index_sources
    assert set(index_sources.values()) == set(CATALOGUE.sources)
    for e in table:
        if e.transform == "carried":
            assert gzip.decompress(carried_file(e.path).read_bytes()) == (data_root / e.path).read_bytes()
        assert e.check == ("uncompressed" if e.path.endswith(".gz") else "file")
        assert bool(e.url) == (e.transform != "carried")
        assert e.url.startswith(RAW) or not e.url


def test_catalogue_rows_are_reproduced_from_the_data_directory(data_root: Path, table: list[FileEntry]) -> None:
    with open(data_root / "index.csv", newline="") as fh:
        notes = {row["path"]: row["notes"] for row in csv.DictReader(fh)}
    picks = sample(table, set(notes))
    for source in ("cmu_li2018", "movingreality", "cmu_iclone"):
        picks += [e for e in table if e.source == source and e.transform != "copy"][:2]
    for e in picks:
        assert catalogue_entry(CATALOGUE, data_root, e.path, notes.get(e.path, "")) == e
        assert sha256(content(data_root / e.path)) == e.sha256


def test_origin_urls_follow_the_documented_layout(table: list[FileEntry]) -> None:
    by_path = {e.path: e.url for e in table}
    li = CATALOGUE.origins["li2018"]
    assert by_path["mocap/cmu_li2018/walking/test_walking_1.bvh"] == (
        f"{RAW}{li.repository}/{li.commit}/data/cmu_mocap/test/walking/walking_1.txt"
    )
    assert by_path["mocap/cmu_iclone/CMU_data.csv"].endswith("/CMU%20data.csv")
    assert by_path["mocap/cmu_iclone/02_01.bvh"].endswith("/All_BVH/subjects/002/002_01.bvh")
    assert by_path["mocap/bandai_namco/dataset-2/dataset-2_walk_normal_001.bvh.gz"].endswith(
        "/dataset/Bandai-Namco-Research-Motiondataset-2/data/dataset-2_walk_normal_001.bvh"
    )
    assert by_path["imu_real/ximu3_lowerbody/pelvis 64F0EDBF (UDP)/Inertial.csv"].endswith(
        "/Examples/logged_lower_body/pelvis%2064F0EDBF%20(UDP)/Inertial.csv"
    )
    assert by_path["imu_real/movingreality/pp01/1Reg/leftfoot.csv.gz"].endswith(
        "/data/1019_pp01/Xsens/exported000/MT_012000E0_000-000_00B4778E.txt"
    )


# ---- the command against a file:// mirror ----


def test_sample_of_every_source_is_rebuilt_byte_identical(sampled, data_root: Path, tmp_path: Path) -> None:
    entries, mirror, sample_table = sampled
    assert {e.source for e in entries} >= set(CATALOGUE.sources)
    dest = tmp_path / "data"
    rc, out = run_get("--dest", dest, "--mirror", mirror.as_uri(), "--table", sample_table, "--jobs", "3")
    assert rc == 0, out
    for e in entries:
        if e.path == "index.csv":
            continue  # it lists the files now there: checked below
        written, original = dest / e.path, data_root / e.path
        assert sha256(content(written)) == e.sha256 == sha256(content(original)), e.path
        if e.check == "file":
            assert written.read_bytes() == original.read_bytes(), e.path
        else:  # deterministic gzip: no time stamp, no name
            assert written.read_bytes()[4:8] == b"\0\0\0\0" and written.read_bytes()[3] == 0, e.path
    with open(dest / "index.csv", newline="") as fh:  # the rows of the files now there
        assert {row["path"] for row in csv.DictReader(fh)} == {e.path for e in entries} & index_paths(data_root)
    for source in CATALOGUE.sources:
        assert f"{source}: " in out
    assert f"[{len(entries)}/{len(entries)} files" in out


def test_corrupted_mirror_file_is_reported_and_fails_the_run(sampled, tmp_path: Path) -> None:
    entries, mirror, sample_table = sampled
    bad = next(e for e in entries if e.source == "gaitmap_foot")
    origin = mirror_path(mirror, bad.url)
    origin.write_bytes(origin.read_bytes()[:-1] + b"#")
    dest = tmp_path / "data"
    rc, out = run_get("--dest", dest, "--mirror", mirror, "--table", sample_table)
    assert rc == 1
    assert f"{bad.path}: sha256 mismatch: expected {bad.sha256}, got {sha256(origin.read_bytes())}" in out
    assert "1 of" in out and "files failed" in out
    assert not (dest / bad.path).exists()
    assert not (dest / "index.csv").exists()  # written only once every file is there
    assert all((dest / e.path).is_file() for e in entries if e is not bad and e.source)


def test_missing_mirror_file_is_reported(sampled, tmp_path: Path) -> None:
    entries, mirror, sample_table = sampled
    gone = next(e for e in entries if e.source == "cmu_raw")
    mirror_path(mirror, gone.url).unlink()
    rc, out = run_get("--dest", tmp_path / "data", "--mirror", mirror, "--table", sample_table)
    assert rc == 1 and f"{gone.path}: FetchError: could not read" in out


def test_rerun_skips_finished_files(sampled, tmp_path: Path) -> None:
    entries, mirror, sample_table = sampled
    dest = tmp_path / "data"
    assert main(["--dest", str(dest), "--mirror", mirror.as_uri(), "--table", str(sample_table)]) == 0
    redo = next(e for e in entries if e.source == "ximu3_lowerbody")
    (dest / redo.path).write_bytes(b"half a file")
    for e in entries:
        if e.url and e is not redo:
            mirror_path(mirror, e.url).unlink()  # only the damaged file can still be fetched
    log = tmp_path / "log.txt"
    with open(log, "w") as stream:
        assert main(["--dest", str(dest), "--mirror", mirror.as_uri(), "--table", str(sample_table)], stream) == 0
    text = log.read_text()
    assert "ximu3_lowerbody: 1 written, 1 already there, 0 failed" in text
    assert "gaitmap_foot: 0 written, 2 already there, 0 failed" in text
    assert sha256((dest / redo.path).read_bytes()) == redo.sha256


def test_sources_option_keeps_their_index_rows(sampled, data_root: Path, tmp_path: Path) -> None:
    entries, mirror, sample_table = sampled
    dest = tmp_path / "data"
    rc, out = run_get("--dest", dest, "--mirror", mirror, "--table", sample_table, "--sources", "cmu_raw,gaitmap_foot")
    assert rc == 0, out
    written = {p.relative_to(dest).parts[0] for p in dest.rglob("*") if p.is_file()}
    assert written == {"mocap", "imu_real", "README.md", "index.csv"}
    with open(dest / "index.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {row["source"] for row in rows} == {"cmu_raw", "gaitmap_foot"}
    assert all((dest / row["path"]).is_file() for row in rows)
    original = (data_root / "index.csv").read_bytes().split(b"\r\n")
    assert set((dest / "index.csv").read_bytes().split(b"\r\n")) <= set(original)  # rows verbatim
    rc, out = run_get("--dest", dest, "--sources", "cmu_raw,nonsense")
    assert rc != 0 and "unknown ['nonsense']" in out


def test_index_of_a_complete_directory_is_the_original(data_root: Path) -> None:
    full = (data_root / "index.csv").read_bytes()
    assert index_of_present_files(full, data_root) == full
    assert index_of_present_files(full, data_root / "mocap").count(b"\r\n") == 1  # header only


def test_the_command_imports_neither_torch_nor_mlflow() -> None:
    code = "import sys, training.data.get; print(sorted({'torch', 'mlflow'} & set(sys.modules)))"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]"


# ---- li2018 exponential-map CSV -> BVH ----


def expmap_csv(frames: list[dict[int, tuple[float, float, float]]], root_asf: list[tuple[float, float, float]]) -> str:
    """li2018 CSV text: a T-pose line 0 (nonzero everywhere, must be dropped), then one line per frame."""
    lines = [",".join(["0.7"] * li2018_bvh.VALUES_PER_ROW)]
    for expmaps, root in zip(frames, root_asf, strict=True):
        values = [*root] + [0.0] * (3 * len(li2018_bvh.SKELETON))
        for node, r in expmaps.items():
            values[3 + 3 * node : 6 + 3 * node] = r
        lines.append(",".join(repr(v) for v in values))
    return "\n".join(lines) + "\n"


def motion_rows(bvh: str) -> list[list[str]]:
    return [line.split() for line in bvh.split("Frame Time: 0.0083333333\n", 1)[1].splitlines()]


def test_li2018_zero_expmaps_give_the_rest_pose_and_metres() -> None:
    bvh = li2018_bvh.csv_to_bvh(expmap_csv([{}], [(1.0, 2.0, -3.0)]))
    (row,) = motion_rows(bvh)  # the T-pose line is gone
    assert "Frames: 1\n" in bvh
    assert row[:3] == ["0.056444", "0.112889", "-0.169333"]  # 1 ASF unit = 0.0254 / 0.45 m
    assert row[3:] == ["0.000000"] * 93 and len(row) == 96


def test_li2018_quarter_turns_give_the_expected_euler_channels() -> None:
    # lfemur (node 2) 90 deg about z, ltibia (node 3) 90 deg about y, lfoot (node 4) 60 deg about x
    # (x is the middle ZXY angle, where 90 deg is the singular case). Local rotation = Rodrigues(r)^T, so the
    # channels carry the negative angles; columns: root 0-5, lhipjoint 6-8, lfemur 9-11, ltibia 12-14, lfoot 15-17.
    frame = {2: (0.0, 0.0, math.pi / 2), 3: (0.0, math.pi / 2, 0.0), 4: (math.pi / 3, 0.0, 0.0)}
    (row,) = motion_rows(li2018_bvh.csv_to_bvh(expmap_csv([frame], [(0.0, 0.0, 0.0)])))
    assert row[9:12] == ["-90.000000", "0.000000", "0.000000"]  # Zrotation Xrotation Yrotation
    assert row[12:15] == ["0.000000", "0.000000", "-90.000000"]
    assert row[15:18] == ["0.000000", "-60.000000", "0.000000"]
    assert set(row[:9] + row[18:]) == {"0.000000"}


def test_li2018_channels_rebuild_the_rotation_and_unwrap_in_time() -> None:
    rng = np.random.default_rng(7)
    rotvecs = rng.normal(size=(50, 3))
    channels = li2018_bvh.euler_zxy_deg(li2018_bvh.local_rotations(rotvecs))
    rebuilt = Rotation.from_euler("ZXY", channels, degrees=True)
    assert np.allclose(rebuilt.as_matrix(), Rotation.from_rotvec(-rotvecs).as_matrix(), atol=1e-12)
    turning = np.radians([[0, 0, 170], [0, 0, 190], [0, 0, 200]])  # about z past 180 deg
    z = li2018_bvh.euler_zxy_deg(li2018_bvh.local_rotations(turning))[:, 0]
    assert np.allclose(z, [-170, -190, -200])


def test_li2018_hierarchy_is_the_stored_one(data_root: Path) -> None:
    stored = (data_root / "mocap/cmu_li2018/running/test_running_1.bvh").read_text()
    assert stored.startswith("\n".join(li2018_bvh.hierarchy_lines()) + "\nMOTION\n")


# ---- Xsens MT Manager text export -> compact CSV ----

MT_HEADER = (
    "// General information: \n"
    "//  MT Manager version: 2019.2.0 \n"
    "//  XDA version: 2019.2.0 build 3853 rev 94535 built on 2019-09-09\n"
    "// Device information: \n"
    "//  DeviceId: 00B4778E\n"
    "//  ProductCode: MTW2-3A7G6\n"
    "//  Firmware Version: 4.6.0\n"
    "//  Hardware Version: 2.0.0\n"
    "// Device settings: \n"
    "//  Filter Profile: human(46.1)\n"
    "//  Option Flags: Orientation Smoother Disabled, AHS Disabled, ICC Disabled\n"
    "// Coordinate system: ENU\n"
    "PacketCounter\tSampleTimeFine\tAcc_X\tAcc_Y\tAcc_Z\tFreeAcc_E\tFreeAcc_N\tFreeAcc_U\tGyr_X\tGyr_Y\tGyr_Z\t"
    "Mag_X\tMag_Y\tMag_Z\tVelInc_X\tVelInc_Y\tVelInc_Z\tQuat_q0\tQuat_q1\tQuat_q2\tQuat_q3\tRoll\tPitch\tYaw\n"
)


def mt_row(counter: int, acc: str, gyr: str, quat: str) -> str:
    """One export row: counter, empty SampleTimeFine, then the 22 channels (FreeAcc, Mag, VelInc, RPY filled)."""
    cells = [str(counter), "", *acc.split(), "0.000000", "0.000000", "-0.077811", *gyr.split()]
    cells += ["-0.629883", "0.436768", "-0.582275", "0.058167", "-0.007822", "0.077667", *quat.split()]
    return "\t".join(cells + ["-5.750857", "-36.692104", "-112.235806"]) + "\n"


MT_EXPORT = MT_HEADER + "".join(
    mt_row(*row)
    for row in [
        (65534, "5.816277 -0.782278 7.767031", "-0.001713 0.011604 0.000974", "0.515376 -0.287521 -0.135722 -0.795801"),
        (
            65535,
            "5.816561 -0.793815 -0.000040",
            "-0.001668 0.011177 0.002712",
            "0.515463 -0.287259 -0.134911 -0.795977",
        ),
        (0, "5.836101 -0.792337 7.762152", "-0.001669 0.011177 0.002711", "0.515529 -0.287356 -0.135331 -0.795828"),
        (1, "nan -0.792337 7.762152", "-0.001669 0.011177 0.002711", "0.515529 -0.287356 -0.135331 -0.795828"),
        (2, "9.390040 4.810439 2.369304", "-0.397725 1.243133 -1.525925", "0.434730 -0.126654 -0.166917 -0.875847"),
    ]
)
MT_CSV = (
    xsens_mt.CSV_HEADER + "\n"
    "0.00,5.8163,-0.7823,7.7670,-0.00171,0.01160,0.00097,0.515376,-0.287521,-0.135722,-0.795801\n"
    "0.01,5.8166,-0.7938,-0.0000,-0.00167,0.01118,0.00271,0.515463,-0.287259,-0.134911,-0.795977\n"
    "0.02,5.8361,-0.7923,7.7622,-0.00167,0.01118,0.00271,0.515529,-0.287356,-0.135331,-0.795828\n"
    "0.04,9.3900,4.8104,2.3693,-0.39772,1.24313,-1.52592,0.434730,-0.126654,-0.166917,-0.875847\n"
)
# The counter wraps at 65536; the row with a NaN is left out; -0.000040 keeps its sign, and a decimal tie such as
# -0.397725 rounds by its binary value (-0.39772499999...), both as in the stored files.
MT_LATE_EXPORT = MT_HEADER + mt_row(1, "0.1 0.2 0.3", "0.0 0.0 0.0", "1.0 0.0 0.0 0.0")
MT_LATE_CSV = (
    f"{xsens_mt.CSV_HEADER}\n0.03,0.1000,0.2000,0.3000,0.00000,0.00000,0.00000,1.000000,0.000000,0.000000,0.000000\n"
)


def test_mt_export_rows_map_to_the_expected_csv_rows() -> None:
    assert xsens_mt.export_to_csv(xsens_mt.read_mt_export(MT_EXPORT)) == MT_CSV


def test_mt_trial_shares_one_time_base_across_the_counter_wrap() -> None:
    out = xsens_mt.convert_trial({"leftfoot": MT_EXPORT, "lumbar": MT_LATE_EXPORT})
    assert out == {"leftfoot": MT_CSV, "lumbar": MT_LATE_CSV}  # the lumbar's first packet came 3 samples later


def test_mt_export_without_a_needed_column_is_refused() -> None:
    with pytest.raises(ValueError, match="missing \\['Quat_q3'\\]"):
        xsens_mt.read_mt_export(MT_EXPORT.replace("\tQuat_q3\t", "\tQuat_qX\t"))


def test_command_converts_li2018_and_movingreality_inputs(tmp_path: Path) -> None:
    """The converted sources through the command: origin-format inputs in the mirror, hand-made expected output."""
    li, mr = CATALOGUE.origins["li2018"], CATALOGUE.origins["movingreality"]
    li_csv = expmap_csv([{}], [(1.0, 2.0, -3.0)])
    bvh = li2018_bvh.csv_to_bvh(li_csv)
    assert bvh.endswith("\n0.056444 0.112889 -0.169333" + " 0.000000" * 93 + "\n")
    mt_dir = "data/1019_pp01/Xsens/exported000"
    trial = "imu_real/movingreality/pp01/1Reg"
    rows = [  # path, source, transform, check, expected content, origin URL, origin content
        ("mocap/cmu_li2018/walking/train_walking_9.bvh", "cmu_li2018", "li2018_bvh", "file", bvh,
         li.url(CATALOGUE.raw_base, "data/cmu_mocap/train/walking/walking_9.txt"), li_csv),
        (f"{trial}/leftfoot.csv.gz", "movingreality", "xsens_mt_csv_gz", "uncompressed", MT_CSV,
         mr.url(CATALOGUE.raw_base, f"{mt_dir}/MT_012000E0_000-000_00B4778E.txt"), MT_EXPORT),
        (f"{trial}/lumbar.csv.gz", "movingreality", "xsens_mt_csv_gz", "uncompressed", MT_LATE_CSV,
         mr.url(CATALOGUE.raw_base, f"{mt_dir}/MT_012000E0_000-000_00B47791.txt"), MT_LATE_EXPORT),
    ]  # fmt: skip
    mirror, entries = tmp_path / "mirror", []
    for path, source, transform, check, expected, url, origin_text in rows:
        entries.append(FileEntry(path, source, transform, check, sha256(expected.encode()), 0, url))
        mirror_path(mirror, url).parent.mkdir(parents=True, exist_ok=True)
        mirror_path(mirror, url).write_text(origin_text)
    write_files_table(entries, tmp_path / "files.csv.gz")
    dest = tmp_path / "data"
    rc, out = run_get("--dest", dest, "--mirror", mirror, "--table", tmp_path / "files.csv.gz")
    assert rc == 0, out
    assert (dest / rows[0][0]).read_text() == bvh
    assert gzip.decompress((dest / rows[1][0]).read_bytes()).decode() == MT_CSV
    assert gzip.decompress((dest / rows[2][0]).read_bytes()).decode() == MT_LATE_CSV
