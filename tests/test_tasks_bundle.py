"""Task bundles (task.yaml + cloud.ply + path.csv): bit-exact round trip, readable CSV,
tampered or truncated files refused with an error naming the file."""

from __future__ import annotations

import csv
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from mmpa.core.errors import InvalidInputError
from mmpa.tasks import (
    FORMAT_VERSION,
    CorruptTaskError,
    TaskExistsError,
    TaskStore,
    UnsupportedVersionError,
    read_bundle,
    write_bundle,
)
from mmpa.tasks.formats import PATH_COLUMNS, csv_to_path, ply_to_cloud
from test_tasks import assert_same_task, make_task


@pytest.fixture
def bundle(tmp_path: Path) -> Path:
    return write_bundle(make_task(), tmp_path / "valve_bundle")


@pytest.mark.parametrize("colors", ["8bit", "none"])
@pytest.mark.parametrize("gripper", [True, False])
def test_store_export_import_is_bit_exact(tmp_path: Path, colors: str, gripper: bool) -> None:
    task = make_task(colors=colors, gripper=gripper)
    with TaskStore(tmp_path / "a.db") as a, TaskStore(tmp_path / "b.db") as b:
        a.save(task)
        out = a.export("valve", tmp_path / "bundle")
        assert out == tmp_path / "bundle"
        assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "path.csv", "task.yaml"]
        back = b.import_bundle(out)
        assert_same_task(task, back)
        assert_same_task(task, b.load("valve"))
        # one metadata checksum across both stores and the bundle
        doc = yaml.safe_load((out / "task.yaml").read_text())
        for s in (a, b):
            row = s.con.execute("SELECT header_sha256, cloud_sha256 FROM tasks").fetchone()
            assert row[0] == doc["header_sha256"]
            assert row[1] == doc["cloud"]["sha256"]
        # the cloud file is the stored blob, byte for byte
        blob = sqlite3.connect(a.path).execute("SELECT ply FROM clouds").fetchone()[0]
        assert (out / "cloud.ply").read_bytes() == bytes(blob)


def test_path_csv_is_readable_and_consistent(bundle: Path) -> None:
    task = make_task()
    rows = list(csv.DictReader((bundle / "path.csv").open()))
    assert tuple(rows[0].keys()) == PATH_COLUMNS
    assert PATH_COLUMNS[:15] == (
        "t", "q1", "q2", "q3", "q4", "q5", "q6",
        "x", "y", "z", "qx", "qy", "qz", "qw", "gripper",
    )  # fmt: skip
    assert len(rows) == len(task.path)
    for i in (0, 17, len(rows) - 1):
        r = rows[i]
        T = task.path.T_arm_base_tool[i]
        assert float(r["t"]) == task.path.t[i]
        assert [float(r[f"q{j}"]) for j in range(1, 7)] == task.path.q[i].tolist()
        assert [float(r[k]) for k in "xyz"] == T[:3, 3].tolist()
        quat = np.array([float(r[k]) for k in ("qx", "qy", "qz", "qw")])
        assert quat[3] >= 0
        # independent check: the quaternion rotates like the stored matrix
        assert np.allclose(Rotation.from_quat(quat).as_matrix(), T[:3, :3], atol=1e-12)
        assert float(r["gripper"]) == task.path.gripper[i]


def test_task_yaml_is_plain_and_exact(bundle: Path) -> None:
    doc = yaml.safe_load((bundle / "task.yaml").read_text())
    task = make_task()
    assert doc["format_version"] == FORMAT_VERSION
    assert doc["name"] == "valve" and doc["site"] == "1"
    assert np.array_equal(np.array(doc["T_map_base_park"]), task.T_map_base_park)
    assert np.array_equal(np.array(doc["q_sample"]), task.q_sample)
    assert doc["cloud"]["bytes"] == (bundle / "cloud.ply").stat().st_size
    assert doc["path"]["n_waypoints"] == 40
    assert b"!!python" not in (bundle / "task.yaml").read_bytes()  # safe YAML only


def test_export_refuses_to_overwrite_a_bundle(tmp_path: Path, bundle: Path) -> None:
    with pytest.raises(TaskExistsError, match=r"already holds a task bundle"):
        write_bundle(make_task(seed=1), bundle)
    write_bundle(make_task(seed=1, site="2"), bundle, overwrite=True)
    assert read_bundle(bundle).site == "2"
    (tmp_path / "file").write_text("x")
    with pytest.raises(InvalidInputError, match=r"not a directory"):
        write_bundle(make_task(), tmp_path / "file")


def test_import_overwrite_semantics(tmp_path: Path, bundle: Path) -> None:
    with TaskStore(tmp_path / "t.db") as s:
        s.save(make_task(seed=3, site="2'"))
        with pytest.raises(TaskExistsError, match=r"'valve' already exists"):
            s.import_bundle(bundle)
        assert s.load("valve").site == "2'"
        s.import_bundle(bundle, overwrite=True)
        assert_same_task(make_task(), s.load("valve"))


def _flip(path: Path, offset: int) -> None:
    b = bytearray(path.read_bytes())
    b[offset] ^= 0x01
    path.write_bytes(bytes(b))


def test_flipped_byte_in_cloud_ply_is_refused(bundle: Path) -> None:
    _flip(bundle / "cloud.ply", -7)
    with pytest.raises(CorruptTaskError, match=r"cloud.ply: SHA-256 mismatch"):
        read_bundle(bundle)


def test_edited_number_in_path_csv_is_refused(bundle: Path) -> None:
    text = (bundle / "path.csv").read_text()
    lines = text.splitlines(keepends=True)
    cells = lines[5].split(",")
    cells[3] = cells[3][:-1] + ("1" if cells[3][-1] != "1" else "2")  # same length
    lines[5] = ",".join(cells)
    (bundle / "path.csv").write_text("".join(lines))
    with pytest.raises(CorruptTaskError, match=r"path.csv: SHA-256 mismatch"):
        read_bundle(bundle)


@pytest.mark.parametrize("name", ["cloud.ply", "path.csv"])
def test_truncated_data_file_is_refused(bundle: Path, name: str) -> None:
    p = bundle / name
    p.write_bytes(p.read_bytes()[:-100])
    with pytest.raises(CorruptTaskError, match=rf"{name}: truncated: \d+ bytes, task.yaml records"):
        read_bundle(bundle)


def test_truncated_or_missing_task_yaml_is_refused(bundle: Path) -> None:
    y = bundle / "task.yaml"
    text = y.read_text()
    y.write_text(text[: len(text) // 2])
    with pytest.raises(CorruptTaskError, match=r"task.yaml"):
        read_bundle(bundle)
    y.unlink()
    with pytest.raises(CorruptTaskError, match=r"task.yaml: missing"):
        read_bundle(bundle)
    with pytest.raises(InvalidInputError, match=r"does not exist"):
        read_bundle(bundle / "nowhere")


def test_missing_data_file_is_refused(bundle: Path) -> None:
    (bundle / "cloud.ply").unlink()
    with pytest.raises(CorruptTaskError, match=r"cloud.ply: missing from the bundle"):
        read_bundle(bundle)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d.update(site="2"), r"metadata checksum mismatch \(header_sha256\)"),
        (lambda d: d["T_map_base_park"][0].__setitem__(3, 9.0), r"header_sha256"),
        (lambda d: d["meta"].update(trials=4), r"header_sha256"),
        (lambda d: d["path"].update(rate_hz=60.0), r"header_sha256"),
        (lambda d: d.pop("q_sample"), r"missing field 'q_sample'"),
        (lambda d: d["cloud"].pop("sha256"), r"missing field 'cloud.sha256'"),
        (lambda d: d["cloud"].update(bytes="many"), r"field 'cloud.bytes' has type str"),
        (lambda d: d["cloud"].update(n_points=3), r"cloud.n_points differs"),
        (lambda d: d.update(name="bad name"), r"task.yaml: name 'bad name' is not a valid"),
        (lambda d: d.update(format_version=FORMAT_VERSION + 1), r"newer than this mmpa"),
    ],
)
def test_edited_task_yaml_is_refused(bundle: Path, edit, match: str) -> None:
    y = bundle / "task.yaml"
    doc = yaml.safe_load(y.read_text())
    edit(doc)
    y.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises((CorruptTaskError, UnsupportedVersionError), match=match):
        read_bundle(bundle)


def test_unedited_yaml_reserialized_still_loads(bundle: Path) -> None:
    """The checks are on values, not on the YAML text: re-dumping the same values is fine."""
    y = bundle / "task.yaml"
    y.write_text(yaml.safe_dump(yaml.safe_load(y.read_text())))
    assert_same_task(make_task(), read_bundle(bundle))


def test_ply_reader_reports_truncation_and_bad_headers() -> None:
    ply = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty double x\n"
           b"property double y\nproperty double z\nend_header\n")  # fmt: skip
    with pytest.raises(CorruptTaskError, match=r"vertex data has 24 bytes.*3 x 24 = 72"):
        ply_to_cloud(ply + bytes(24))
    cloud = ply_to_cloud(ply + np.arange(9, dtype="<f8").tobytes())
    assert np.array_equal(cloud.points, np.arange(9.0).reshape(3, 3)) and cloud.colors is None
    with pytest.raises(CorruptTaskError, match=r"not binary_little_endian"):
        ply_to_cloud(ply.replace(b"binary_little_endian", b"ascii") + bytes(72))
    with pytest.raises(CorruptTaskError, match=r"not a PLY file"):
        ply_to_cloud(b"hello")


def test_csv_reader_names_row_and_column() -> None:
    task = make_task(n_waypoints=5)
    from mmpa.tasks.formats import path_to_csv

    text = path_to_csv(task.path).decode()
    lines = text.splitlines()
    bad = lines[2].split(",")
    bad[2] = "abc"
    lines[2] = ",".join(bad)
    with pytest.raises(CorruptTaskError, match=r"row 3, column 'q2': 'abc' is not a number"):
        csv_to_path("\n".join(lines).encode(), 30.0)
    lines = text.splitlines()
    row = lines[3].split(",")
    row[PATH_COLUMNS.index("qw")] = str(-float(row[PATH_COLUMNS.index("qw")]) + 0.5)
    lines[3] = ",".join(row)
    with pytest.raises(CorruptTaskError, match=r"row 4: quaternion .* disagree"):
        csv_to_path("\n".join(lines).encode(), 30.0)
    with pytest.raises(CorruptTaskError, match=r"header must be"):
        csv_to_path(b"a,b\n1,2\n", 30.0)
