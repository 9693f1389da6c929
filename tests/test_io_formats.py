"""LAS/LAZ and E57 readers, the writers of every output format, gctr apply and register --aligned."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import REPO, rotation

from gctr_cli import cli
from gctr_cli.geometry import apply, to_matrix
from gctr_cli.io import (
    SUPPORTED_EXTENSIONS,
    WRITE_EXTENSIONS,
    MatrixError,
    PointCloud,
    PointCloudError,
    load_point_cloud,
    read_matrix,
    read_point_cloud,
    transform_cloud,
    write_aligned,
    write_matrix,
    write_point_cloud,
)

laspy = pytest.importorskip("laspy")
pye57 = pytest.importorskip("pye57")

BUNNY = REPO / "data" / "models" / "bunny.ply"
UTM = np.array([500_000.0, 5_400_000.0, 300.0])


def utm_las(path: Path, n: int = 2000, seed: int = 0, version: str = "1.2", point_format: int = 3):
    """A LAS/LAZ file with UTM offsets and millimetre scale; returns the exact expected coordinates
    (X * scale + offset, computed in float64) and the stored intensity / colours."""
    rng = np.random.default_rng(seed)
    hdr = laspy.LasHeader(point_format=point_format, version=version)
    hdr.scales = np.array([0.001, 0.001, 0.001])
    hdr.offsets = UTM.copy()
    las = laspy.LasData(hdr)
    ints = [rng.integers(-(10**7), 10**7, n), rng.integers(-(10**7), 10**7, n), rng.integers(0, 10**5, n)]
    las.X, las.Y, las.Z = ints
    las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    las.classification = rng.integers(0, 20, n).astype(np.uint8)
    las.red = rng.integers(0, 65535, n).astype(np.uint16)
    las.green = rng.integers(0, 65535, n).astype(np.uint16)
    las.blue = rng.integers(0, 65535, n).astype(np.uint16)
    las.write(path)
    expected = np.stack([ints[j] * 0.001 + UTM[j] for j in range(3)], axis=1)
    return expected, las


# ----------------------------------------------------------------------------------------------------
# LAS / LAZ
# ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, version, fmt", [("tile.las", "1.2", 3), ("tile.laz", "1.2", 3),
                                                ("tile14.las", "1.4", 7), ("tile14.laz", "1.4", 7)])
def test_las_laz_keep_utm_coordinates_exactly_and_attributes(tmp_path, name, version, fmt):
    expected, las = utm_las(tmp_path / name, version=version, point_format=fmt)
    cloud = read_point_cloud(tmp_path / name)
    np.testing.assert_array_equal(cloud.points, expected)  # bit-exact: no float32 anywhere
    assert cloud.points.dtype == np.float64
    np.testing.assert_array_equal(cloud.attributes["intensity"], las.intensity)
    np.testing.assert_array_equal(cloud.attributes["classification"], np.asarray(las.classification))
    np.testing.assert_array_equal(cloud.attributes["red"], las.red)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / name), expected)


def test_las_truncated_and_lying_headers_are_refused_before_allocating(tmp_path):
    _expected, _ = utm_las(tmp_path / "ok.las", n=500)
    data = (tmp_path / "ok.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[: len(data) - 100])
    with pytest.raises(PointCloudError, match=r"cut\.las: truncated: the header declares 500 points"):
        load_point_cloud(tmp_path / "cut.las")
    big = bytearray(data)
    big[107:111] = (4_000_000_000).to_bytes(4, "little")  # legacy point count: 4 billion points
    (tmp_path / "huge.las").write_bytes(bytes(big))
    with pytest.raises(PointCloudError, match=r"huge\.las: truncated: the header declares 4000000000 points"):
        load_point_cloud(tmp_path / "huge.las")
    (tmp_path / "text.las").write_text("1 2 3\n" * 100)
    with pytest.raises(PointCloudError, match=r"text\.las: not a LAS/LAZ file"):
        load_point_cloud(tmp_path / "text.las")
    (tmp_path / "stub.las").write_bytes(data[:100])  # cut inside the header: the signature is there
    with pytest.raises(PointCloudError, match=r"stub\.las: truncated LAS file: 100 bytes, but the LAS header alone"):
        load_point_cloud(tmp_path / "stub.las")


@pytest.mark.parametrize("version, fmt", [("1.2", 3), ("1.4", 7)])
def test_las_records_beyond_the_declared_count_are_named(tmp_path, caplog, version, fmt):
    """A header count below the records present cut LAS files without a word (ASCII PLY/PCD warn); a
    count of 0 said 'contains no points'. LAS 1.4 counts the records up to the first EVLR."""
    expected, las = utm_las(tmp_path / "ok.las", n=5000, version=version, point_format=fmt)
    if version == "1.4":  # an EVLR after the points is not a point record
        las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("acme", 1, "notes", bytes(300))])
        las.write(tmp_path / "ok.las")
    data = bytearray((tmp_path / "ok.las").read_bytes())
    at, size = (247, 8) if version == "1.4" else (107, 4)  # the 64-bit count of LAS 1.4, else the legacy one
    for count in (4000, 0):
        data[at : at + size] = count.to_bytes(size, "little")
        (tmp_path / f"n{count}.las").write_bytes(bytes(data))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "n4000.las"), expected[:4000])
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'n4000.las'}: 1000 more point records after the 4000 points the header declares (ignored)"]
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "n0.las")
    assert str(ei.value) == (f"{tmp_path / 'n0.las'}: the header declares 0 points but 5000 point records follow "
                             "(a writer that never filled in the point count?)")


def test_laz_chunks_beyond_the_declared_count_are_named(tmp_path, caplog):
    """LAZ chunks hold 50,000 points: the chunk table (a few bytes) shows a count short by more than a chunk;
    a smaller shortfall is known only by decompressing, and is not told."""
    expected, _ = utm_las(tmp_path / "ok.laz", n=120_000)
    data = bytearray((tmp_path / "ok.laz").read_bytes())
    for count in (40_000, 119_000):
        data[107:111] = count.to_bytes(4, "little")
        (tmp_path / f"n{count}.laz").write_bytes(bytes(data))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    np.testing.assert_array_equal(load_point_cloud(tmp_path / "n40000.laz"), expected[:40_000])
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'n40000.laz'}: at least 60001 more point records after the 40000 points the header declares "
        "(ignored)"]
    caplog.clear()
    assert len(load_point_cloud(tmp_path / "n119000.laz")) == 119_000
    assert not caplog.records


def test_laz_lying_point_count_and_corrupt_data(tmp_path):
    utm_las(tmp_path / "ok.laz", n=3000)
    data = bytearray((tmp_path / "ok.laz").read_bytes())
    lie = bytearray(data)
    lie[107:111] = (4_000_000_000).to_bytes(4, "little")
    (tmp_path / "lie.laz").write_bytes(bytes(lie))
    with pytest.raises(PointCloudError, match=r"lie\.laz: corrupt LAZ header: it declares 4000000000 points"):
        load_point_cloud(tmp_path / "lie.laz")
    garbage = bytearray(data)
    start = int.from_bytes(data[96:100], "little")
    garbage[start + 50 :] = bytes(np.random.default_rng(0).integers(0, 256, len(data) - start - 50, dtype=np.uint8))
    (tmp_path / "garbage.laz").write_bytes(bytes(garbage))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "garbage.laz")
    msg = str(ei.value)
    assert "garbage.laz" in msg and ("corrupt" in msg or "truncated" in msg), msg
    assert "Error" not in msg and "Exception" not in msg, msg


@pytest.mark.parametrize("cut", [100, 20_000, 200_000])
def test_a_truncated_laz_file_is_called_truncated(tmp_path, cut):
    """An interrupted copy or download of a LAZ file ends before the chunk table its point data point to;
    it was reported only as 'corrupt or unsupported LAZ file: the point data cannot be decompressed'."""
    utm_las(tmp_path / "ok.laz", n=120_000)
    data = (tmp_path / "ok.laz").read_bytes()
    table = int.from_bytes(data[int.from_bytes(data[96:100], "little"):][:8], "little")
    (tmp_path / "cut.laz").write_bytes(data[: len(data) - cut])
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "cut.laz")
    assert str(ei.value) == (f"{tmp_path / 'cut.laz'}: truncated or corrupt LAZ file: its chunk table should start "
                             f"at byte {table} but the file has only {len(data) - cut} bytes (an interrupted copy "
                             "or download?)")


WKT = ('PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
       'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
       'PARAMETER["central_meridian",15],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],'
       'UNIT["metre",1],AUTHORITY["EPSG","32633"]]')
#: a GeoTIFF key directory (version 1.1.0, one key): ProjectedCSTypeGeoKey = EPSG 32633
GEOKEYS = np.array([1, 1, 0, 1, 3072, 0, 1, 32633], dtype="<u2").tobytes()


def riegl_las(path: Path, n: int = 3000, extra_vlrs=()):
    """LAS 1.4 point format 6 as a survey scanner writes it: a WKT CRS record, adjusted standard GPS
    time, system identifier, file source id, a private VLR and EVLR; returns the LasData written."""
    rng = np.random.default_rng(4)
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales, hdr.offsets = np.array([0.001] * 3), UTM.copy()
    hdr.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    hdr.global_encoding.wkt = True
    hdr.system_identifier = "RIEGL VQ-1560"
    hdr.file_source_id = 17
    hdr.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(WKT))
    hdr.vlrs.append(laspy.VLR("acme", 7, "flight line", b"line 12"))
    hdr.vlrs.extend(extra_vlrs)
    # 76,800 bytes: too long for a VLR
    hdr.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.VLR("acme", 8, "trajectory", bytes(range(256)) * 300)])
    las = laspy.LasData(hdr)
    las.X, las.Y = rng.integers(-(10**6), 10**6, n), rng.integers(-(10**6), 10**6, n)
    las.Z = rng.integers(0, 10**5, n)
    las.gps_time = 3.0e8 + np.arange(n) * 1e-5
    las.write(path)
    return las


@pytest.mark.parametrize("ext", [".las", ".laz"])
@pytest.mark.parametrize("moved", [False, True])
def test_las_output_keeps_the_source_crs_gps_time_type_and_ids(tmp_path, ext, moved):
    """Even an identity apply wrote GPS time type 0, no WKT bit, no records, system id 'OTHER': readers
    then misread adjusted standard GPS time and the tile had no CRS."""
    src = riegl_las(tmp_path / f"src{ext}")
    T = to_matrix(1.0, rotation([0, 0, 1], 3), [4.0, -2.0, 0.5]) if moved else np.eye(4)
    write_aligned(tmp_path / f"src{ext}", T, tmp_path / f"out{ext}")
    out = laspy.read(tmp_path / f"out{ext}")
    assert (str(out.header.version), out.header.point_format.id) == ("1.4", 6)
    assert out.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    assert out.header.global_encoding.wkt
    assert (out.header.system_identifier, out.header.file_source_id) == ("RIEGL VQ-1560", 17)
    assert [(v.user_id, v.record_id, bytes(v.record_data_bytes())) for v in out.header.vlrs] == [
        ("LASF_Projection", 2112, WKT.encode() + b"\0"), ("acme", 7, b"line 12")]
    assert [(v.user_id, v.record_id, v.record_data) for v in out.evlrs] == [("acme", 8, bytes(range(256)) * 300)]
    np.testing.assert_array_equal(out.gps_time, src.gps_time)
    np.testing.assert_allclose(out.xyz, apply(T, np.asarray(src.xyz)), rtol=0, atol=1e-3)


def test_las_1_2_keeps_version_format_and_geokeys_drops_a_stale_index_and_other_formats_warn(tmp_path, caplog):
    """A LAS 1.2 format 3 tile stays LAS 1.2 format 3 with its GeoTIFF keys; a COPC index record, which
    would describe the old file's point order, is left out with a warning; a PLY output says that the CRS
    is not kept."""
    _expected, _ = utm_las(tmp_path / "in.las", n=500)
    las = laspy.read(tmp_path / "in.las")
    las.header.vlrs.append(laspy.VLR("LASF_Projection", 34735, "GeoKeyDirectoryTag", GEOKEYS))
    las.header.vlrs.append(laspy.VLR("copc", 1, "copc info", bytes(160)))
    las.header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    las.write(tmp_path / "geo.las")
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_aligned(tmp_path / "geo.las", np.eye(4), tmp_path / "out.las")
    out = laspy.read(tmp_path / "out.las")
    assert (str(out.header.version), out.header.point_format.id) == ("1.2", 3)
    assert out.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    assert [(v.user_id, v.record_id, bytes(v.record_data_bytes())) for v in out.header.vlrs] == [
        ("LASF_Projection", 34735, GEOKEYS)]
    np.testing.assert_array_equal(out.red, las.red)
    write_aligned(tmp_path / "geo.las", np.eye(4), tmp_path / "out.ply")
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'out.las'}: not kept from the LAS source: the COPC info record",
        f"{tmp_path / 'out.ply'}: the coordinate reference system of the LAS source (GeoTIFF keys, EPSG 32633) "
        "is not kept: PLY files cannot hold it"]


def survey_laz(path: Path, n: int = 200_000, scales=(0.001, 0.001, 0.001)):
    """A LAZ tile of a smooth surface (as airborne tiles compress) with millimetre scale and UTM offsets."""
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 500, (n, 2))
    z = 20 * np.sin(xy[:, 0] / 50) + 10 * np.cos(xy[:, 1] / 70) + rng.normal(0, 0.05, n) + 120
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales, hdr.offsets = np.array(scales), np.array([500_000.0, 4_000_000.0, 0.0])
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = xy[:, 0] + 500_000, xy[:, 1] + 4_000_000, z
    las.write(path)
    return las


def test_las_output_keeps_the_source_quantum_and_size(tmp_path):
    """From a millimetre source, the writer chose 1e-7/1e-8 scales: an identity apply of a LAZ grew it
    ~1.9-fold (12.3 -> 23.1 MB for 2M points) with digits the source never had. Now the source's scale
    and offset are kept: the same integers, the same size."""
    src = survey_laz(tmp_path / "tile.laz")
    write_aligned(tmp_path / "tile.laz", np.eye(4), tmp_path / "same.laz")
    out = laspy.read(tmp_path / "same.laz")
    np.testing.assert_array_equal(out.header.scales, [0.001] * 3)
    np.testing.assert_array_equal(out.header.offsets, [500_000.0, 4_000_000.0, 0.0])
    for dim in ("X", "Y", "Z"):
        np.testing.assert_array_equal(out[dim], src[dim])
    size_in, size_out = (tmp_path / "tile.laz").stat().st_size, (tmp_path / "same.laz").stat().st_size
    assert size_out < 1.02 * size_in, (size_in, size_out)


@pytest.mark.parametrize("scale, shift, expected_scales", [
    (1.0, [3.0, -4.0, 0.5], [0.01, 0.01, 0.001]),  # rigid: x and y mix x and y (1 cm), z stays z (1 mm)
    (2.5, [3.0, -4.0, 0.5], [0.02, 0.02, 0.002]),  # 2.5 cm rounded down to 2 cm, 2.5 mm to 2 mm
    (1.0, [3e7, 0.0, 0.0], [0.01, 0.01, 0.001]),  # x moved 30,000 km: the source's x offset no longer fits int32
])
def test_las_output_quantum_follows_the_transform_scale(tmp_path, scale, shift, expected_scales):
    survey_laz(tmp_path / "tile.laz", n=5000, scales=(0.01, 0.01, 0.001))
    T = to_matrix(scale, rotation([0, 0, 1], 30), shift)
    moved = write_aligned(tmp_path / "tile.laz", T, tmp_path / "out.las")
    out = laspy.read(tmp_path / "out.las")
    np.testing.assert_array_equal(out.header.scales, expected_scales)
    err = np.abs(np.asarray(out.xyz) - moved.points)
    assert (err <= np.array(expected_scales) / 2 * (1 + 1e-6)).all(), err.max(axis=0)  # half a step
    offsets = [500_000.0, 4_000_000.0, 0.0]  # the source's, where they fit
    if shift[0] > 1e6:  # a whole number of 1000 steps below the minimum
        offsets[0] = np.floor(moved.points[:, 0].min() / 10.0) * 10.0
    np.testing.assert_array_equal(out.header.offsets, offsets)


def test_laz_without_room_for_its_temporary_copy_says_so_instead_of_corrupt(tmp_path, monkeypatch):
    """A LAZ file is decompressed to a temporary LAS copy; when that copy could not be written (a full
    /tmp, ``ulimit -f``) a valid file was called 'corrupt or unsupported LAZ file'."""
    import errno
    import resource
    import tempfile

    from gctr_cli.io import las as las_module

    utm_las(tmp_path / "ok.laz", n=20_000)  # 680 KB of point records uncompressed
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    real = las_module._decompress

    def file_size_limit(path, out):  # runs in the forked child only: a 64 KB file-size limit, as ulimit -f
        resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))
        real(path, out)

    monkeypatch.setattr(las_module, "_decompress", file_size_limit)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "ok.laz")
    assert str(ei.value) == (f"{tmp_path / 'ok.laz'}: cannot decompress the LAZ file: no space for its temporary "
                             f"copy in {tmp_path} (needs about 1 MB; set TMPDIR to a folder with room)")

    def refused(path, out):
        raise PermissionError(errno.EACCES, "Permission denied", str(out))

    monkeypatch.setattr(las_module, "_decompress", refused)
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "ok.laz")
    assert str(ei.value) == (f"{tmp_path / 'ok.laz'}: cannot decompress the LAZ file: no permission to write its "
                             f"temporary copy in {tmp_path} (set TMPDIR to a writable folder)")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "gone"))
    with pytest.raises(PointCloudError) as ei:
        load_point_cloud(tmp_path / "ok.laz")
    assert str(ei.value) == (f"{tmp_path / 'ok.laz'}: cannot decompress the LAZ file: cannot create a temporary "
                             f"folder in {tmp_path / 'gone'} (No such file or directory; set TMPDIR to a writable "
                             "folder with room)")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(las_module, "_decompress", real)
    assert len(load_point_cloud(tmp_path / "ok.laz")) == 20_000


def test_las_extra_dimensions_of_several_elements_and_scaled_ones_are_kept(tmp_path):
    """A 3-element extra dimension (normals, 3 doubles) was missing from LAS and PLY outputs, and a scaled
    one (u2 × 0.1) came back as float64: now LAS gets the source's own declarations; the normals are turned
    with the cloud."""
    n = 500
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.add_extra_dims([laspy.ExtraBytesParams("height", "f8"), laspy.ExtraBytesParams("normals", "3f8"),
                        laspy.ExtraBytesParams("amplitude", "u2", description="dB", scales=np.array([0.1]),
                                               offsets=np.array([0.0]))])
    las = laspy.LasData(hdr)
    rng = np.random.default_rng(8)
    las.x, las.y, las.z = rng.normal(size=(3, n)) * 10
    las.height = rng.normal(size=n)
    las.normals = rng.normal(size=(n, 3))
    las.amplitude = rng.integers(0, 6000, n) / 10
    las.write(tmp_path / "extra.las")
    T = to_matrix(1.0, rotation([1, 0, 0], 20), [1.0, 2.0, 3.0])
    write_aligned(tmp_path / "extra.las", T, tmp_path / "out.las")
    out = laspy.read(tmp_path / "out.las")
    assert [(d.name, d.type_str(), None if d.scales is None else list(d.scales), d.description)
            for d in out.point_format.extra_dimensions] == [
        ("height", "f8", None, ""), ("normals", "3f8", None, ""), ("amplitude", "u2", [0.1], "dB")]
    # the normals turn with the surface (kept unturned they were wrong for the moved cloud)
    turned = np.asarray(las.normals) @ T[:3, :3].T
    turned /= np.linalg.norm(turned, axis=1, keepdims=True)
    np.testing.assert_allclose(out.normals, turned, atol=1e-12)
    np.testing.assert_array_equal(out.points.array["amplitude"], las.points.array["amplitude"])  # the same integers
    write_aligned(tmp_path / "extra.las", T, tmp_path / "out.ply")
    ply = read_point_cloud(tmp_path / "out.ply").attributes  # as nx ny nz, the names PLY readers know
    np.testing.assert_allclose(np.column_stack([ply["nx"], ply["ny"], ply["nz"]]), turned, atol=1e-12)
    np.testing.assert_allclose(ply["amplitude"], las.amplitude)


def test_a_las_1_0_source_is_written_as_1_2(tmp_path):
    """laspy writes LAS 1.1-1.4 only: keeping a 1.0 source's version crashed the writer with laspy's
    FileVersionNotSupported. 1.2 has the same header and point formats 0 and 1."""
    hdr = laspy.LasHeader(point_format=1, version="1.2")
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = np.random.default_rng(3).uniform(0, 10, (3, 100))
    las.write(tmp_path / "v12.las")
    raw = bytearray((tmp_path / "v12.las").read_bytes())
    raw[25] = 0  # the minor version byte: LAS 1.0
    (tmp_path / "v10.las").write_bytes(bytes(raw))
    write_aligned(tmp_path / "v10.las", np.eye(4), tmp_path / "out.las")
    out = laspy.read(tmp_path / "out.las")
    assert str(out.header.version) == "1.2" and out.point_format.id == 1
    np.testing.assert_allclose(out.x, las.x, atol=0.0005)


def test_las_output_quantum_follows_each_axis_stretch(tmp_path):
    """A matrix that shrinks one axis more than the others (feet to metres in z only) keeps that axis's
    digits: one scale factor for all axes (the cube root of the determinant) gave z a quantum coarser than
    its data (0.82 of a source quantum off)."""
    hdr = laspy.LasHeader(point_format=6, version="1.4")
    hdr.scales, hdr.offsets = np.array([0.001] * 3), np.zeros(3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = np.random.default_rng(4).uniform(0, 100, (3, 500))
    las.write(tmp_path / "ft.las")
    T = np.diag([1.0, 1.0, 0.3048, 1.0])
    write_aligned(tmp_path / "ft.las", T, tmp_path / "m.las")
    out = laspy.read(tmp_path / "m.las")
    assert out.header.scales[2] <= 0.001 * 0.3048
    np.testing.assert_allclose(out.z, np.asarray(las.z) * 0.3048, atol=out.header.scales[2] / 2 + 1e-12)


def test_scan_angle_rank_fills_the_scan_angle_of_formats_6_to_10(tmp_path):
    """Formats 0-5 store the scan angle in whole degrees (scan_angle_rank), 6-10 in 0.006° steps
    (scan_angle): a rank went into an extra dimension and the standard scan angle was written 0."""
    pts = np.random.default_rng(9).normal(size=(20, 3))
    rank = np.arange(-45, 55, 5, dtype=np.int8)
    write_point_cloud(tmp_path / "out.las", PointCloud(pts, {"scan_angle_rank": rank}))
    out = laspy.read(tmp_path / "out.las")
    assert out.point_format.id == 6 and not list(out.point_format.extra_dimension_names)
    np.testing.assert_array_equal(out.scan_angle, np.round(rank / 0.006))
    np.testing.assert_allclose(out.scan_angle * 0.006, rank, atol=0.003)
    # and back: a format 6 scan angle into a format 1 file (the source's format)
    hdr = laspy.LasHeader(point_format=1, version="1.2")
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.write(tmp_path / "pf1.las")
    cloud = read_point_cloud(tmp_path / "pf1.las")
    attrs = {k: v for k, v in cloud.attributes.items() if k != "scan_angle_rank"}
    attrs["scan_angle"] = np.round(rank / 0.006).astype(np.int16)
    write_point_cloud(tmp_path / "back.las", PointCloud(cloud.points, attrs, "las", cloud.meta))
    back = laspy.read(tmp_path / "back.las")
    assert back.point_format.id == 1 and not list(back.point_format.extra_dimension_names)
    np.testing.assert_array_equal(back.scan_angle_rank, rank)


# ----------------------------------------------------------------------------------------------------
# E57
# ----------------------------------------------------------------------------------------------------


def quat(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = np.radians(angle_deg) / 2
    return np.array([np.cos(h), *(np.sin(h) * axis)])  # w x y z, as E57 stores it


def test_e57_merges_every_scan_with_its_pose(tmp_path):
    rng = np.random.default_rng(2)
    # pye57 stores cartesian coordinates as float32: use float32 values so the file holds them exactly
    scans = [rng.normal(size=(300, 3)).astype(np.float32).astype(np.float64),
             (rng.normal(size=(200, 3)) * 2).astype(np.float32).astype(np.float64)]
    poses = [(quat([0, 0, 1], 0), UTM), (quat([1, 2, 3], 70), UTM + [25.0, -13.0, 2.0])]
    e = pye57.E57(str(tmp_path / "project.e57"), mode="w")
    for pts, (q, t) in zip(scans, poses):
        e.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2],
                          "intensity": np.linspace(0, 1, len(pts))}, rotation=q, translation=t)
    e.close()
    cloud = read_point_cloud(tmp_path / "project.e57")
    expected = np.vstack([pts @ rotation(q[1:], 2 * np.degrees(np.arccos(q[0]))).T + t if q[0] < 1 else pts + t
                          for pts, (q, t) in zip(scans, poses)])
    assert cloud.points.shape == (500, 3)
    np.testing.assert_allclose(cloud.points, expected, rtol=0, atol=1e-8)  # float64 all the way: 10 nm at UTM size
    assert cloud.attributes["intensity"].shape == (500,)


def test_e57_says_which_scans_it_merged_what_it_drops_and_which_fields_it_does_not_keep(tmp_path, caplog):
    """Intensity disappeared without a word when one of several scans lacked it, and so did the points
    flagged invalid and the fields gctr does not read (row/column indices)."""
    rng = np.random.default_rng(3)
    e = pye57.E57(str(tmp_path / "site.e57"), mode="w")
    a, b = rng.normal(size=(300, 3)), rng.normal(size=(200, 3))
    state = np.zeros(300, np.int8)
    state[::10] = 2  # 30 points without coordinates
    e.write_scan_raw({"cartesianX": a[:, 0], "cartesianY": a[:, 1], "cartesianZ": a[:, 2], "intensity": np.ones(300),
                      "cartesianInvalidState": state, "rowIndex": np.arange(300) // 20,
                      "columnIndex": np.arange(300) % 20}, name="Station 1")
    e.write_scan_raw({"cartesianX": b[:, 0], "cartesianY": b[:, 1], "cartesianZ": b[:, 2]}, name="Station 2",
                     translation=np.array([5.0, 0.0, 0.0]))
    e.close()
    caplog.set_level("INFO", logger="gctr_cli.io")
    cloud = read_point_cloud(tmp_path / "site.e57")
    assert len(cloud) == 470 and "intensity" not in cloud.attributes
    path = tmp_path / "site.e57"
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [
        ("WARNING", f"{path}: not kept: intensity (missing from scan 1 'Station 2'; kept only when every scan has "
                    "it); 'columnIndex', 'rowIndex' (point fields gctr does not read)"),
        ("INFO", f"{path}: merged 2 scans, each placed by its pose: scan 0 'Station 1', scan 1 'Station 2'"),
        ("WARNING", f"{path}: dropped 30 of 500 points the E57 file flags invalid (no coordinates measured)")]
    caplog.clear()
    load_point_cloud(path)  # coordinates only: no word about attributes
    assert [r.levelname for r in caplog.records] == ["INFO", "WARNING"]


def test_e57_scan_with_an_invalid_pose_is_named(tmp_path):
    """A zero quaternion would put every point at the scan's translation ("all points identical"):
    the error names the scan and its pose instead."""
    pts = np.random.default_rng(0).normal(size=(100, 3))
    e = pye57.E57(str(tmp_path / "pose.e57"), mode="w")
    e.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]},
                     rotation=np.zeros(4), translation=np.array([1.0, 2.0, 3.0]))
    e.close()
    with pytest.raises(PointCloudError, match=r"pose\.e57: scan 0 has an invalid pose \(rotation quaternion"):
        load_point_cloud(tmp_path / "pose.e57")


def test_e57_corrupt_files_name_the_file_in_words(tmp_path):
    (tmp_path / "text.e57").write_text("1 2 3\n" * 50)
    with pytest.raises(PointCloudError, match=r"text\.e57: not an E57 file"):
        load_point_cloud(tmp_path / "text.e57")
    pts = np.random.default_rng(0).normal(size=(100, 3))
    e = pye57.E57(str(tmp_path / "ok.e57"), mode="w")
    e.write_scan_raw({"cartesianX": pts[:, 0], "cartesianY": pts[:, 1], "cartesianZ": pts[:, 2]})
    e.close()
    data = (tmp_path / "ok.e57").read_bytes()
    (tmp_path / "cut.e57").write_bytes(data[: len(data) // 2])
    bad = bytearray(data)
    bad[len(data) // 3 : len(data) // 3 + 64] = b"\xff" * 64
    (tmp_path / "flipped.e57").write_bytes(bytes(bad))
    for name in ("cut.e57", "flipped.e57"):
        with pytest.raises(PointCloudError) as ei:
            load_point_cloud(tmp_path / name)
        msg = str(ei.value)
        assert name in msg and "E57" in msg, msg
        assert "Exception" not in msg and "Error" not in msg, msg


def _e57_with_colours(path: Path, scans: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]]) -> None:
    """Scans ``(points, rgb, invalid state, top)`` whose colours are integers 0..``top`` (pye57's writer
    allows only 0..255), without ``colorLimits`` (the prototype's range says the depth)."""
    import uuid

    from pye57 import libe57

    e = pye57.E57(str(path), mode="w")
    imf = e.image_file
    for pts, rgb, state, top in scans:
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
        proto = libe57.StructureNode(imf)
        for a in "XYZ":
            proto.set(f"cartesian{a}", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, -1e3, 1e3))
        for c in ("Red", "Green", "Blue"):
            proto.set(f"color{c}", libe57.IntegerNode(imf, 0, 0, top))
        proto.set("cartesianInvalidState", libe57.IntegerNode(imf, 0, 0, 2))
        points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
        scan.set("points", points)
        e.data3d.append(scan)
        arrays = [np.ascontiguousarray(pts[:, j]) for j in range(3)]
        arrays += [np.ascontiguousarray(rgb[:, j], dtype=np.uint16) for j in range(3)]
        arrays.append(np.ascontiguousarray(state, dtype=np.int8))
        names = ["cartesianX", "cartesianY", "cartesianZ", "colorRed", "colorGreen", "colorBlue",
                 "cartesianInvalidState"]
        buffers = libe57.VectorSourceDestBuffer()
        for name, arr in zip(names, arrays):
            buffers.append(libe57.SourceDestBuffer(imf, name, arr, len(pts), True, True))
        writer = points.writer(buffers)
        writer.write(len(pts))
        writer.close()
    e.close()


@pytest.mark.parametrize("top", [255, 65535])
def test_e57_colours_of_8_and_16_bits_are_read_with_their_points(tmp_path, top):
    """pye57 reads colours into 8-bit buffers, so a scan with 16-bit colours (the standard allows any
    limits) registered but was "corrupt or unsupported" as soon as its attributes were read (gctr
    apply, an aligned output). Colours follow their points when invalid points are dropped."""
    rng = np.random.default_rng(4)
    pts = rng.normal(size=(400, 3))
    rgb = rng.integers(0, top + 1, size=(400, 3))
    state = np.zeros(400, np.int8)
    state[::7] = 1
    _e57_with_colours(tmp_path / "scan.e57", [(pts, rgb, state, top)])
    cloud = read_point_cloud(tmp_path / "scan.e57")
    keep = state == 0
    np.testing.assert_array_equal(cloud.points, pts[keep])
    for j, name in enumerate(("red", "green", "blue")):
        assert cloud.attributes[name].dtype == (np.uint8 if top == 255 else np.uint16)
        np.testing.assert_array_equal(cloud.attributes[name], rgb[keep, j])
    write_point_cloud(tmp_path / "out.ply", cloud)  # PLY readers expect 8 bits: the high byte
    back = read_point_cloud(tmp_path / "out.ply")
    np.testing.assert_array_equal(back.attributes["red"], rgb[keep, 0] >> (8 if top > 255 else 0))


def test_e57_scans_of_different_colour_depths_are_merged_at_one_scale(tmp_path):
    """An 8-bit scan beside a 16-bit one: merged raw, the 8-bit scan's white (255) read as 255 of 65535,
    nearly black. Each scan is read by its own range; 12-bit colours are stretched to 16 bits."""
    rng = np.random.default_rng(5)
    a, b, c = rng.normal(size=(100, 3)), rng.normal(size=(80, 3)) + 5, rng.normal(size=(60, 3)) - 5
    full = np.ones((100, 3), int)
    _e57_with_colours(tmp_path / "mixed.e57", [(a, full * 255, np.zeros(100), 255),
                                               (b, full[:80] * 65535, np.zeros(80), 65535),
                                               (c, full[:60] * 4095, np.zeros(60), 4095)])
    cloud = read_point_cloud(tmp_path / "mixed.e57")
    assert cloud.attributes["green"].dtype == np.uint16
    np.testing.assert_array_equal(cloud.attributes["green"], np.full(240, 65535))


# ----------------------------------------------------------------------------------------------------
# writers
# ----------------------------------------------------------------------------------------------------


@pytest.fixture
def rich_cloud():
    rng = np.random.default_rng(5)
    n = 300
    pts = rng.normal(size=(n, 3)) * 10 + UTM
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    attrs = {"intensity": rng.integers(0, 60000, n).astype(np.uint16),
             "red": rng.integers(0, 256, n).astype(np.uint8), "green": rng.integers(0, 256, n).astype(np.uint8),
             "blue": rng.integers(0, 256, n).astype(np.uint8),
             "nx": normals[:, 0].astype(np.float32), "ny": normals[:, 1].astype(np.float32),
             "nz": normals[:, 2].astype(np.float32)}
    return PointCloud(pts, attrs)


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz", ".csv", ".las"])
def test_attribute_names_beyond_ascii_are_written_in_ascii(tmp_path, caplog, ext):
    """A PLY property named ``intensité`` (UTF-8 in the header, as current tools write it) ended every
    writer but LAS in a UnicodeEncodeError traceback: in a batch the pair's good matrix was lost."""
    rng = np.random.default_rng(6)
    pts = rng.normal(size=(50, 3))
    header = ("ply\nformat ascii 1.0\nelement vertex 50\nproperty double x\nproperty double y\n"
              "property double z\nproperty float intensité\nproperty float höhe_über_grund\nend_header\n")
    values = rng.random((50, 2)).astype(np.float32)
    rows = "".join(" ".join(repr(float(x)) for x in (*p, *v)) + "\n" for p, v in zip(pts, values))
    (tmp_path / "src.ply").write_bytes((header + rows).encode("utf-8"))
    cloud = read_point_cloud(tmp_path / "src.ply")
    assert "intensité" in cloud.attributes  # read as UTF-8, not as Latin-1 mojibake
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / f"out{ext}", cloud)
    assert "'intensité' as 'intensite'" in caplog.text
    back = read_point_cloud(tmp_path / f"out{ext}")
    np.testing.assert_allclose(back.attributes["intensite"], values[:, 0], rtol=1e-6)
    np.testing.assert_allclose(back.attributes["hohe_uber_grund"], values[:, 1], rtol=1e-6)


def test_las_extra_dimension_names_are_cut_to_32_bytes_and_standard_names_match_any_case(tmp_path, caplog):
    """A name longer than an ExtraBytes record's 32 bytes ended in a traceback from laspy; a PLY's
    ``Intensity`` and ``Red Green Blue`` went to extra dimensions, leaving the standard ones 0."""
    rng = np.random.default_rng(7)
    n = 80
    names = ["scalar_C2C_absolute_distances_(XY)", "scalar_C2C_absolute_distances_(Z)",
             "a_very_long_scalar_field_name_of_40_chars", "a_very_long_scalar_field_name_of_41_chars"]
    attrs = {k: rng.random(n) for k in names}
    attrs.update({"Intensity": rng.integers(0, 4000, n).astype(np.uint16),
                  "Red": rng.integers(0, 256, n).astype(np.uint8), "Green": rng.integers(0, 256, n).astype(np.uint8),
                  "Blue": rng.integers(0, 256, n).astype(np.uint8), "Classification": rng.random(n)})
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / "out.las", PointCloud(rng.normal(size=(n, 3)), attrs))
    las = laspy.read(tmp_path / "out.las")
    assert las.point_format.id == 7
    np.testing.assert_array_equal(las.intensity, attrs["Intensity"])
    np.testing.assert_array_equal(las.red, attrs["Red"].astype(np.uint16) * 257)
    written = ["scalar_C2C_absolute_distances_XY", "scalar_C2C_absolute_distances_Z",
               "a_very_long_scalar_field_name_of", "a_very_long_scalar_field_name_2"]
    # fractions cannot fill the standard classification: kept as an extra dimension, under their own name
    assert sorted(las.point_format.extra_dimension_names) == sorted([*written, "Classification"])
    for old, new in zip(names, written):
        np.testing.assert_array_equal(las[new], attrs[old])
        assert f"{old!r} as {new!r}" in caplog.text


def test_ply_writes_64_bit_integers_as_32_bits_when_they_fit_and_warns_when_double_loses_digits(tmp_path, caplog):
    """PLY has no 64-bit integer: nanosecond time stamps written as double became 97 distinct values of
    8171 without a word."""
    n = 100
    stamps = np.int64(1_700_000_000_123_456_789) + np.arange(n, dtype=np.int64) * 3
    attrs = {"timestamp": stamps, "point_id": np.arange(n, dtype=np.int64), "offset": -np.arange(n, dtype=np.int64),
             "flag": np.arange(n) % 2 == 0}
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / "out.ply", PointCloud(np.random.default_rng(8).normal(size=(n, 3)), attrs))
    back = read_point_cloud(tmp_path / "out.ply").attributes
    assert back["point_id"].dtype == np.uint32 and back["offset"].dtype == np.int32 and back["flag"].dtype == np.uint8
    np.testing.assert_array_equal(back["point_id"], attrs["point_id"])
    np.testing.assert_array_equal(back["offset"], attrs["offset"])
    np.testing.assert_array_equal(back["flag"], attrs["flag"])
    assert back["timestamp"].dtype == np.float64
    assert "attribute 'timestamp' written as double, which keeps integers up to 2^53 exactly" in caplog.text
    assert "point_id" not in caplog.text and "offset" not in caplog.text


def test_las_names_never_land_on_coordinates_or_standard_dimensions_and_colours_map_only_when_they_fit(
        tmp_path, caplog):
    """Review of the renaming: ``(z)`` became ``z`` (a laspy traceback), ``classification*`` filled the
    standard classification; ``Red Green Blue`` in 0..1 were mapped to LAS colours and then dropped as not
    fitting (before, extra dimensions); a LAS 1.2 source's extra ``Red Green Blue`` turned the output into
    LAS 1.4 format 7."""
    rng = np.random.default_rng(9)
    n = 60
    pts = rng.normal(size=(n, 3))
    attrs = {"(z)": rng.random(n), "ẑ": rng.random(n), "classification*": rng.integers(0, 9, n).astype(np.int32),
             "Red": rng.random(n), "Green": rng.random(n), "Blue": rng.random(n)}
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / "out.las", PointCloud(pts, attrs))
    las = laspy.read(tmp_path / "out.las")
    assert las.point_format.id == 6  # float colours do not fit LAS's: no colour format, kept as extra dimensions
    assert sorted(las.point_format.extra_dimension_names) == sorted(["z_2", "z_3", "classification_2", "Red",
                                                                     "Green", "Blue"])
    np.testing.assert_array_equal(las["z_2"], attrs["(z)"])
    np.testing.assert_array_equal(las["classification_2"], attrs["classification*"])
    np.testing.assert_array_equal(las["Red"], attrs["Red"])
    assert not las.classification.any()
    np.testing.assert_allclose(las.z, pts[:, 2], atol=1e-6)
    assert "not written" not in caplog.text
    # every other format: ``ẑ`` is no coordinate either
    write_point_cloud(tmp_path / "out.ply", PointCloud(pts, {"ẑ": attrs["ẑ"]}))
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "out.ply").attributes["z_2"], attrs["ẑ"])

    # a LAS 1.2 source whose extra dimensions are named Red Green Blue keeps its version and format
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.add_extra_dims([laspy.ExtraBytesParams(name=c, type="u2", description="camera") for c in
                           ("Red", "Green", "Blue")])
    src = laspy.LasData(header)
    src.x, src.y, src.z = pts.T
    for c in ("Red", "Green", "Blue"):
        src[c] = rng.integers(0, 65536, n).astype(np.uint16)
    src.write(tmp_path / "pf1.las")
    write_point_cloud(tmp_path / "back.las", read_point_cloud(tmp_path / "pf1.las"))
    back = laspy.read(tmp_path / "back.las")
    assert (str(back.header.version), back.point_format.id) == ("1.2", 1)
    assert sorted(back.point_format.extra_dimension_names) == ["Blue", "Green", "Red"]
    np.testing.assert_array_equal(back["Red"], src["Red"])


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_ply_pcd_writers_keep_coordinates_and_every_attribute(tmp_path, rich_cloud, ext):
    write_point_cloud(tmp_path / f"out{ext}", rich_cloud)
    back = read_point_cloud(tmp_path / f"out{ext}")
    np.testing.assert_array_equal(back.points, rich_cloud.points)
    pcd_normals = {"nx": "normal_x", "ny": "normal_y", "nz": "normal_z"} if ext == ".pcd" else {}
    for k, v in rich_cloud.attributes.items():
        name = pcd_normals.get(k, k)  # PCD names normals the PCL way
        np.testing.assert_array_equal(back.attributes[name], v, err_msg=k)
        assert back.attributes[name].dtype == v.dtype, k


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_writer_quantises_finely_and_keeps_standard_and_extra_attributes(tmp_path, rich_cloud, ext):
    write_point_cloud(tmp_path / f"out{ext}", rich_cloud)
    back = read_point_cloud(tmp_path / f"out{ext}")
    span = np.ptp(rich_cloud.points, axis=0)
    assert (np.abs(back.points - rich_cloud.points) <= span / 4e8 + 1e-9).all()  # half a decimal step
    np.testing.assert_array_equal(back.attributes["intensity"], rich_cloud.attributes["intensity"])
    np.testing.assert_array_equal(back.attributes["red"], rich_cloud.attributes["red"].astype(np.uint16) * 257)
    np.testing.assert_array_equal(back.attributes["nx"], rich_cloud.attributes["nx"])  # extra bytes



def test_las_writer_stretches_unit_float_intensity_and_never_wraps(tmp_path, caplog):
    """laspy casts without a word: a float intensity in [0, 1] (E57, Open3D) became 0 and 70000
    became 4464. Now the unit intensity fills 0..65535 and what does not fit is named, not written."""
    pts = np.random.default_rng(2).normal(size=(10, 3))
    for unit in ([0.0, 0.25, 0.5, 0.999, 1.0] * 2, [0.0, 1.0] * 5):  # whole-valued floats in [0, 1] too
        write_point_cloud(tmp_path / "unit.laz", PointCloud(pts, {"intensity": np.array(unit)}))
        np.testing.assert_array_equal(read_point_cloud(tmp_path / "unit.laz").attributes["intensity"],
                                      np.round(np.array(unit) * 65535))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    attrs = {"intensity": np.array([1, 2, 3, 4, 70000] * 2), "classification": np.array([0.0, 1.5, 2, 3, 4] * 2),
             "user_data": np.array([1.0, 2.0, 3.0, 4.0, 5.0] * 2), "point_source_id": np.full(10, 2**64 - 1, np.uint64),
             "flag": np.array([True, False] * 5), "label": np.array(["a"] * 10), "half": np.ones(10, np.float16)}
    write_point_cloud(tmp_path / "bad.las", PointCloud(pts, attrs))
    back = read_point_cloud(tmp_path / "bad.las").attributes
    for k in ("intensity", "classification", "point_source_id"):
        assert not back[k].any(), k  # left empty, not wrapped
    np.testing.assert_array_equal(back["user_data"], [1, 2, 3, 4, 5] * 2)  # whole floats fit
    np.testing.assert_array_equal(back["flag"], [1, 0] * 5)  # flags as 0/1 extra bytes
    assert back["half"].dtype == np.float32 and (back["half"] == 1).all()  # laspy has no float16 extra bytes
    out = tmp_path / "bad.las"
    assert sorted(r.getMessage() for r in caplog.records) == sorted([
        f"{out}: attribute 'intensity' holds a value LAS dimension 'intensity' cannot (70000; it holds whole "
        "numbers 0..65535); not written",
        f"{out}: attribute 'classification' holds a value LAS dimension 'classification' cannot (1.5; it holds "
        "whole numbers 0..255); not written",
        f"{out}: attribute 'point_source_id' holds a value LAS dimension 'point_source_id' cannot "
        "(18446744073709551615; it holds whole numbers 0..65535); not written",
        f"{out}: attributes not written (not numeric): label"])  # said for every format (write_point_cloud)


def test_a_pts_intensity_is_shifted_into_las_range_with_a_warning(tmp_path, caplog):
    """Leica's PTS intensity runs -2048..2047; written to LAS it was dropped whole ("holds a value LAS
    dimension 'intensity' cannot (-1683 ...)"). Now a .pts file's intensity becomes (value + 2048) x 16,
    0..65520, told — every value, so that a scan with no negative value maps as its siblings do. Another
    file's negative intensities are no PTS values: dropped, as before."""
    pts = np.random.default_rng(3).normal(size=(12, 3))
    caplog.set_level("WARNING", logger="gctr_cli.io")
    for name, values in (("dark", [-2048, -1683, -1, 0, 5, 2047] * 2), ("bright", [0, 5, 100, 2047] * 3)):
        (tmp_path / f"{name}.pts").write_text("12\n" + "".join(f"{x} {y} {z} {i}\n" for (x, y, z), i in
                                                                zip(pts, values, strict=True)))
        write_point_cloud(tmp_path / f"{name}.las", read_point_cloud(tmp_path / f"{name}.pts"))
        np.testing.assert_array_equal(read_point_cloud(tmp_path / f"{name}.las").attributes["intensity"],
                                      (np.array(values) + 2048) * 16)
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / name}.las: intensity -2048..2047 (the PTS convention) written as (value + 2048) x 16, "
        "LAS's 0..65535" for name in ("dark", "bright")]
    caplog.clear()
    (tmp_path / "other.xyz").write_text("# x y z intensity\n" + "".join(
        f"{x} {y} {z} {i}\n" for (x, y, z), i in zip(pts, [-3, -2, -1, 0, 1, 2] * 2, strict=True)))
    write_point_cloud(tmp_path / "other.las", read_point_cloud(tmp_path / "other.xyz"))
    assert not read_point_cloud(tmp_path / "other.las").attributes["intensity"].any()
    assert "holds a value LAS dimension 'intensity' cannot (-3;" in caplog.text


@pytest.mark.parametrize("ext", [".xyz", ".pts", ".txt"])
def test_text_writers_round_trip_exactly_with_attribute_columns(tmp_path, rich_cloud, ext):
    write_point_cloud(tmp_path / f"out{ext}", rich_cloud)
    np.testing.assert_array_equal(load_point_cloud(tmp_path / f"out{ext}"), rich_cloud.points)
    text = (tmp_path / f"out{ext}").read_text()
    if ext == ".pts":  # no comment line: PTS readers take the columns by their number (tests/test_io_text.py)
        assert "#" not in text and text.splitlines()[1].count(" ") == 6
    else:
        assert "# x y z intensity red green blue nx ny nz" in text


def test_every_read_extension_is_listed_and_writers_cover_all_but_e57():
    assert set(SUPPORTED_EXTENSIONS) == {".ply", ".pcd", ".xyz", ".pts", ".txt", ".csv", ".las", ".laz", ".e57"}
    assert set(WRITE_EXTENSIONS) == set(SUPPORTED_EXTENSIONS) - {".e57"}


def test_transform_rotates_normals_and_moves_utm_points_precisely(rich_cloud):
    T = to_matrix(2.0, rotation([1, 1, 0], 30), [-499_000.0, 10.0, 3.0])
    moved = transform_cloud(rich_cloud, T)
    exact = apply(T, rich_cloud.points - UTM) + T[:3, :3] @ UTM  # reference without the big offset
    np.testing.assert_allclose(moved.points, exact, rtol=0, atol=1e-9 * np.abs(exact).max())
    n0 = np.stack([rich_cloud.attributes[k] for k in ("nx", "ny", "nz")], 1).astype(np.float64)
    n1 = np.stack([moved.attributes[k] for k in ("nx", "ny", "nz")], 1).astype(np.float64)
    np.testing.assert_allclose(n1, n0 @ rotation([1, 1, 0], 30).T, atol=1e-6)
    np.testing.assert_array_equal(moved.attributes["intensity"], rich_cloud.attributes["intensity"])


def test_transform_keeps_normals_perpendicular_under_a_shear_or_a_mirror():
    # the plane z = 0.5 x + 0.25 y, normals stored as nx ny nz; a shear and a mirror move points and normals
    # differently: the normals must stay perpendicular to the moved plane (rotated by A, they would not)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1, 1, (200, 2))
    pts = np.c_[xy, 0.5 * xy[:, 0] + 0.25 * xy[:, 1]]
    n = np.array([-0.5, -0.25, 1.0]) / np.linalg.norm([-0.5, -0.25, 1.0])
    cloud = PointCloud(pts, {k: np.full(200, v, np.float32) for k, v in zip(("nx", "ny", "nz"), n, strict=True)})
    for A in (np.array([[1.0, 0.8, 0.0], [0.0, 1.0, 0.0], [0.0, 0.3, 2.0]]), np.diag([-1.0, 1.0, 1.0])):
        T = np.eye(4)
        T[:3, :3] = A
        moved = transform_cloud(cloud, T)
        m = np.stack([moved.attributes[k] for k in ("nx", "ny", "nz")], 1).astype(np.float64)
        edges = moved.points[1:] - moved.points[0]
        assert np.abs(edges @ m[0]).max() < 1e-6 * np.abs(edges).max()  # perpendicular to the moved plane
        np.testing.assert_allclose(np.linalg.norm(m, axis=1), 1, atol=1e-6)
        assert m[0] @ (A @ n) > 0  # still on the same side of the surface


def test_write_aligned_checks_matrix_and_output_before_reading(tmp_path, rich_cloud):
    write_point_cloud(tmp_path / "in.ply", rich_cloud)
    T = to_matrix(0.5, rotation([0, 0, 1], 90), [1.0, 2.0, 3.0])
    moved = write_aligned(tmp_path / "in.ply", T, tmp_path / "sub" / "out.laz")
    assert len(moved) == 300 and (tmp_path / "sub" / "out.laz").exists()
    with pytest.raises(PointCloudError, match=r"out\.e57: unsupported extension '\.e57' for writing"):
        write_aligned(tmp_path / "missing.ply", T, tmp_path / "out.e57")
    with pytest.raises(MatrixError, match="last row"):
        write_aligned(tmp_path / "in.ply", np.ones((4, 4)), tmp_path / "x.ply")


# ----------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------


def test_gctr_apply_writes_the_moved_cloud_in_the_output_format(tmp_path, rich_cloud):
    write_point_cloud(tmp_path / "scan.laz", rich_cloud)
    T = to_matrix(1.5, rotation([0, 1, 0], 20), [10.0, -5.0, 0.25])
    write_matrix(tmp_path / "T.txt", T)
    res = CliRunner().invoke(cli.main, ["apply", str(tmp_path / "T.txt"), str(tmp_path / "scan.laz"),
                                        "-o", str(tmp_path / "moved.ply")])
    assert res.exit_code == 0, res.output
    assert "moved.ply (300 points)" in res.output
    src = read_point_cloud(tmp_path / "scan.laz")
    out = read_point_cloud(tmp_path / "moved.ply")
    np.testing.assert_allclose(out.points, apply(T, src.points), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(out.attributes["intensity"], src.attributes["intensity"])

    res = CliRunner().invoke(cli.main, ["apply", str(tmp_path / "T.txt"), str(tmp_path / "scan.laz"),
                                        "-o", str(tmp_path / "moved.obj")])
    assert res.exit_code == 2 and "moved.obj: cannot write a point cloud with extension '.obj'" in res.output
    res = CliRunner().invoke(cli.main, ["apply", str(tmp_path / "nope.txt"), str(tmp_path / "scan.laz"),
                                        "-o", str(tmp_path / "m.ply")])
    assert res.exit_code == 2 and "nope.txt: file does not exist" in res.output


def bunny_pair(folder: Path):
    """bunny.ply as a LAZ source and, moved by a UTM-size similarity, as a two-scan E57 target."""
    src = load_point_cloud(BUNNY)
    T = to_matrix(2.5, rotation([1, -2, 0.5], 50), UTM + [3.0, -7.0, 0.0])
    tgt = apply(T, src)
    write_point_cloud(folder / "a.laz", PointCloud(src, {"intensity": np.arange(len(src), dtype=np.uint16)}))
    e = pye57.E57(str(folder / "b.e57"), mode="w")
    q, t = quat([0, 0, 1], 35), UTM + [10.0, 4.0, -1.0]
    Rq = rotation([0, 0, 1], 35)
    for part in (tgt[::2], tgt[1::2]):  # two scans, same pose, stored in scanner coordinates
        loc = (part - t) @ Rq
        e.write_scan_raw({"cartesianX": loc[:, 0], "cartesianY": loc[:, 1], "cartesianZ": loc[:, 2]},
                         rotation=q, translation=t)
    e.close()
    write_matrix(folder / "gt.txt", T)
    return src, T


@pytest.mark.engine
def test_register_laz_onto_e57_writes_the_aligned_cloud(tmp_path):
    """End to end through the real CLI and engine: LAZ source, two-scan E57 target at UTM size."""
    src, T = bunny_pair(tmp_path)
    res = CliRunner().invoke(cli.main, ["register", str(tmp_path / "a.laz"), str(tmp_path / "b.e57"),
                                        "--gt", str(tmp_path / "gt.txt"), "-o", str(tmp_path / "m.txt"),
                                        "--aligned", str(tmp_path / "out.ply")])
    assert res.exit_code == 0, res.output
    assert "success: true" in res.output
    T_est = read_matrix(tmp_path / "m.txt")
    out = read_point_cloud(tmp_path / "out.ply")
    a = read_point_cloud(tmp_path / "a.laz")
    np.testing.assert_allclose(out.points, apply(T_est, a.points), rtol=0, atol=1e-6)  # the matrix, applied
    diag = np.linalg.norm(np.ptp(apply(T, src), axis=0))
    assert np.linalg.norm(out.points - apply(T, a.points), axis=1).max() < 0.01 * diag  # close to the truth
    np.testing.assert_array_equal(out.attributes["intensity"], a.attributes["intensity"])


def test_register_aligned_with_unwritable_extension_fails_before_registering(tmp_path, monkeypatch):
    import gctr_cli.engine
    from data_scripts import fake_engine

    monkeypatch.setattr(gctr_cli.engine, "register", fake_engine.register)
    called = []
    monkeypatch.setattr(fake_engine, "register", functools.partial(called.append))
    res = CliRunner().invoke(cli.main, ["register", str(BUNNY), str(BUNNY), "--aligned", str(tmp_path / "x.e57")])
    assert res.exit_code == 2 and "x.e57: cannot write a point cloud with extension '.e57'" in res.output
    assert not called


def test_manifest_pairs_las_laz_e57_files(tmp_path):
    for d in ("src", "tgt"):
        (tmp_path / d).mkdir()
    for stem, ext in (("a", ".laz"), ("b", ".las")):
        (tmp_path / "src" / f"{stem}{ext}").write_bytes(b"x")
        (tmp_path / "tgt" / f"{stem}.e57").write_bytes(b"x")
    res = CliRunner().invoke(cli.main, ["manifest", str(tmp_path / "src"), str(tmp_path / "tgt"),
                                        "-o", str(tmp_path / "pairs.csv")])
    assert res.exit_code == 0, res.output
    text = (tmp_path / "pairs.csv").read_text()
    assert "a,src/a.laz,tgt/a.e57" in text and "b,src/b.las,tgt/b.e57" in text


@pytest.mark.parametrize("offset, size, data", [(0.0, 4, "binary"), (4.5e6, 8, "ascii")])
def test_aligned_pcd_files_open_in_open3d(tmp_path, offset, size, data):
    """Open3D's legacy reader returns zeros for float64 binary PCD: aligned clouds near the origin are
    written as binary float32 (within 1e-7 of the extent); UTM-size ones as ASCII float64, which Open3D
    reads exactly."""
    import open3d as o3d

    rng = np.random.default_rng(5)
    pts = rng.uniform(-1.0, 1.0, size=(500, 3)) + offset
    write_point_cloud(tmp_path / "in.ply", pts)
    T = np.eye(4)
    T[:3, 3] = [0.25, -0.5, 0.125]
    moved = write_aligned(tmp_path / "in.ply", T, tmp_path / "out.pcd")
    header = (tmp_path / "out.pcd").read_bytes().split(b"DATA")[0].decode()
    assert f"SIZE {size} {size} {size}" in header
    assert (tmp_path / "out.pcd").read_bytes().split(b"DATA ")[1].startswith(data.encode())
    back = read_point_cloud(tmp_path / "out.pcd").points
    np.testing.assert_allclose(back, moved.points, rtol=0, atol=1e-7 * 2.0)
    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(tmp_path / "out.pcd")).points),
                               moved.points, rtol=0, atol=1e-6 if size == 4 else 0.0)


@pytest.mark.parametrize("names, out_name, expected", [
    (("nx", "ny", "nz"), "out.pcd", ("normal_x", "normal_y", "normal_z")),
    (("normal_x", "normal_y", "normal_z"), "out.ply", ("nx", "ny", "nz")),
])
def test_normals_converted_between_formats_are_found_by_open3d(tmp_path, names, out_name, expected):
    """PLY readers look for ``nx ny nz`` and PCD readers for ``normal_x ...``: an aligned cloud written
    in the other format renames its normals, so Open3D finds them, rotated with the cloud."""
    import open3d as o3d

    rng = np.random.default_rng(8)
    pts = rng.uniform(-1.0, 1.0, size=(300, 3))
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    attrs = {n: normals[:, j] for j, n in enumerate(names)}
    attrs["intensity"] = rng.uniform(0, 1, 300).astype(np.float32)
    src = tmp_path / ("in.ply" if out_name.endswith(".pcd") else "in.pcd")
    write_point_cloud(src, PointCloud(pts, attrs))
    R = rotation([1.0, 2.0, -0.5], 40.0)
    T = np.eye(4)
    T[:3, :3] = 2.0 * R
    write_aligned(src, T, tmp_path / out_name)
    assert set(expected) <= set(read_point_cloud(tmp_path / out_name).attributes)
    o3d_cloud = o3d.io.read_point_cloud(str(tmp_path / out_name))
    assert o3d_cloud.has_normals()
    np.testing.assert_allclose(np.asarray(o3d_cloud.normals), normals @ R.T, rtol=0, atol=1e-6)


def test_a_stray_attribute_named_like_the_other_normals_is_not_overwritten(tmp_path):
    """A PLY's ``nx ny nz`` are not renamed to PCD's ``normal_x ...`` when a column ``normal_x`` exists
    already: both keep their values (the normals rotated), nothing is mixed."""
    rng = np.random.default_rng(9)
    pts = rng.uniform(-1.0, 1.0, size=(50, 3))
    normals = np.tile([0.0, 0.0, 1.0], (50, 1))
    stray = np.full(50, 7.0)
    write_point_cloud(tmp_path / "in.ply", PointCloud(pts, {"nx": normals[:, 0], "ny": normals[:, 1],
                                                            "nz": normals[:, 2], "normal_x": stray}))
    T = np.eye(4)
    T[:3, :3] = rotation([1.0, 0.0, 0.0], 90.0)
    write_aligned(tmp_path / "in.ply", T, tmp_path / "out.pcd")
    back = read_point_cloud(tmp_path / "out.pcd").attributes
    np.testing.assert_array_equal(back["normal_x"], stray)
    moved = np.stack([back[n] for n in ("nx", "ny", "nz")], axis=1)
    np.testing.assert_allclose(moved, normals @ T[:3, :3].T, atol=1e-6)


@pytest.mark.parametrize("out_name", ["out.pcd", "out.ply"])
@pytest.mark.parametrize("widening", [257, 256, 1])
def test_sixteen_bit_las_colours_become_eight_bit_colours_open3d_reads(tmp_path, out_name, widening):
    """LAS colours are 16-bit (8-bit values ×257 or ×256, or plain 8-bit values in 16-bit fields); PLY
    and PCD readers expect 8 bits, so a LAS cloud written as PLY/PCD gets their high byte (or narrowed)."""
    import open3d as o3d

    rng = np.random.default_rng(10)
    pts = rng.uniform(-1.0, 1.0, size=(200, 3))
    rgb8 = rng.integers(0, 256, size=(200, 3)).astype(np.uint16)
    stored = rgb8 * widening
    write_point_cloud(tmp_path / "in.las", PointCloud(pts, {k: stored[:, j].astype(np.uint16)
                                                            for j, k in enumerate(("red", "green", "blue"))}))
    assert read_point_cloud(tmp_path / "in.las").attributes["red"].dtype == np.uint16
    write_aligned(tmp_path / "in.las", np.eye(4), tmp_path / out_name)
    back = read_point_cloud(tmp_path / out_name).attributes
    np.testing.assert_array_equal(np.stack([back[k] for k in ("red", "green", "blue")], axis=1), rgb8)
    colours = np.asarray(o3d.io.read_point_cloud(str(tmp_path / out_name)).colors)
    np.testing.assert_allclose(colours, rgb8 / 255.0, atol=1e-6)


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_ascii_files_written_in_several_blocks_round_trip_exactly(tmp_path, rich_cloud, ext, monkeypatch):
    """ASCII rows are formatted a block at a time; with blocks smaller than the cloud, the file is the
    same as written in one block and reads back exactly."""
    import gctr_cli.io.ply as ply

    write_point_cloud(tmp_path / f"one{ext}", rich_cloud, binary=False)
    monkeypatch.setattr(ply, "TEXT_BLOCK_ROWS", 7)
    write_point_cloud(tmp_path / f"blocks{ext}", rich_cloud, binary=False)
    assert (tmp_path / f"blocks{ext}").read_bytes() == (tmp_path / f"one{ext}").read_bytes()
    np.testing.assert_array_equal(read_point_cloud(tmp_path / f"blocks{ext}").points, rich_cloud.points)


def test_aligned_output_does_not_repeat_the_readers_warnings(tmp_path, monkeypatch):
    """`register --aligned` (and `batch --write-aligned`) read the source a second time to move it:
    the warning about its non-finite rows was printed twice, the second time without the pair."""
    import gctr_cli.engine
    from data_scripts import fake_engine

    monkeypatch.setattr(gctr_cli.engine, "register", fake_engine.register)
    pts = read_point_cloud(BUNNY).points[:500].copy()
    pts[:3] = np.nan
    np.savetxt(tmp_path / "nan.xyz", pts)
    res = CliRunner().invoke(cli.main, ["register", str(tmp_path / "nan.xyz"), str(BUNNY),
                                        "--aligned", str(tmp_path / "out.ply")])
    assert res.exit_code == 0, res.output
    assert res.output.count("dropped 3 of 500 points with non-finite") == 1, res.output
    assert len(read_point_cloud(tmp_path / "out.ply")) == 497
    write_matrix(tmp_path / "identity.txt", np.eye(4))
    res = CliRunner().invoke(cli.main, ["apply", str(tmp_path / "identity.txt"), str(tmp_path / "nan.xyz"),
                                        "-o", str(tmp_path / "moved.ply")])
    assert res.exit_code == 0, res.output
    assert res.output.count("dropped 3 of 500 points with non-finite") == 1, res.output  # apply's only read
    # ... but a note about an attribute, which the registration's read (coordinates only) never gave, is shown
    rows = "".join(f"{x!r} {y!r} {z!r} {250 + i % 10}\n" for i, (x, y, z) in enumerate(pts[3:].tolist()))
    header = ("ply\nformat ascii 1.0\nelement vertex 497\nproperty float64 x\nproperty float64 y\n"
              "property float64 z\nproperty uint8 red\nend_header\n")
    (tmp_path / "wide.ply").write_text(header + rows)
    res = CliRunner().invoke(cli.main, ["register", str(tmp_path / "wide.ply"), str(BUNNY),
                                        "--aligned", str(tmp_path / "wide_out.ply")])
    assert res.exit_code == 0, res.output
    assert res.output.count("'red' is declared uint8 but holds values it cannot (e.g. 256; range 0..255") == 1


def test_the_reread_filter_keeps_other_threads_warnings(caplog):
    """`write_aligned(..., reread=True)` silences its own read's warnings, not another thread's."""
    import logging
    import threading

    from gctr_cli.io import _NotesDropped

    log = logging.getLogger("gctr_cli.io")
    caplog.set_level("WARNING", logger="gctr_cli.io")
    with _NotesDropped():
        log.warning("this thread: dropped")
        worker = threading.Thread(target=log.warning, args=("another thread: kept",))
        worker.start()
        worker.join()
        log.error("this thread: an error is kept")
    log.warning("after: kept")
    assert [r.getMessage() for r in caplog.records] == ["another thread: kept", "this thread: an error is kept",
                                                        "after: kept"]


@pytest.mark.parametrize("ext", [".ply", ".pcd", ".xyz", ".csv", ".las"])
def test_text_attributes_are_named_in_a_warning_not_dropped_silently(tmp_path, caplog, ext):
    """No format holds text per point; an API user's ``label`` column was left out of every output but LAS
    without a word."""
    pts = np.random.default_rng(1).uniform(size=(20, 3))
    cloud = PointCloud(pts, {"label": np.array([f"p{i}" for i in range(20)]), "intensity": np.arange(20.0)})
    caplog.set_level("WARNING", logger="gctr_cli.io")
    write_point_cloud(tmp_path / f"out{ext}", cloud)
    assert [r.getMessage() for r in caplog.records] == [f"{tmp_path / f'out{ext}'}: attributes not written (not "
                                                         "numeric): label"]
    back = read_point_cloud(tmp_path / f"out{ext}")
    np.testing.assert_allclose(back.points, pts, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(back.attributes["intensity"], dtype=float), np.arange(20.0))
