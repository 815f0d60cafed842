"""dtm_labeler.ros.pointcloud: PointCloud2 <-> numpy over arbitrary layouts (no node needed)."""
import array
import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from dtm_labeler.ros.pointcloud import (
    DATATYPES,
    PointCloudError,
    cloud_to_structured,
    make_labeled_cloud,
    make_xyz_cloud,
    read_points_xyz,
)

F32, F64 = PointField.FLOAT32, PointField.FLOAT64
I8, U8, I16, U16 = PointField.INT8, PointField.UINT8, PointField.INT16, PointField.UINT16
I32, U32 = PointField.INT32, PointField.UINT32
PAD_BYTE = 0xEE  # padding is filled with garbage so that reading it by mistake shows


def build_cloud(columns, layout, point_step, height, width, row_pad=0, bigendian=False,
                pad_last_row=True):
    """Hand-pack a PointCloud2 from ``columns`` {name: (n,) or (n, count)} and ``layout``
    [(name, datatype, count, offset)], independently of the module under test."""
    order = ">" if bigendian else "<"
    dt = np.dtype({
        "names": [name for name, *_ in layout],
        "formats": [DATATYPES[d].newbyteorder(order) if c == 1
                    else np.dtype((DATATYPES[d].newbyteorder(order), (c,)))
                    for _, d, c, _ in layout],
        "offsets": [o for *_, o in layout],
        "itemsize": point_step,
    })
    n = height * width
    raw = np.full(n * point_step, PAD_BYTE, dtype=np.uint8)
    rec = raw.view(dt)
    for name, *_ in layout:
        rec[name] = columns[name]
    rows = raw.reshape(height, width * point_step)
    data = np.hstack([rows, np.full((height, row_pad), PAD_BYTE, np.uint8)]).reshape(-1)
    if not pad_last_row and row_pad:
        data = data[:-row_pad]
    msg = PointCloud2()
    msg.height, msg.width = height, width
    msg.fields = [PointField(name=name, datatype=d, count=c, offset=o) for name, d, c, o in layout]
    msg.is_bigendian = bigendian
    msg.point_step = point_step
    msg.row_step = width * point_step + row_pad
    msg.is_dense = False
    msg.data = array.array("B", data.tobytes())
    return msg


def _xyz(n, seed=0):
    return np.random.default_rng(seed).uniform(-3, 3, size=(n, 3))


# ------------------------------------------------------------------------------- round trips

def test_xyz_round_trip_and_header():
    xyz = _xyz(40)
    hdr = Header(frame_id="mocap")
    hdr.stamp.sec, hdr.stamp.nanosec = 12, 345
    msg = make_xyz_cloud(xyz, header=hdr)
    assert isinstance(msg, PointCloud2)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 40, 12, 480)
    assert [f.name for f in msg.fields] == ["x", "y", "z"]
    assert all(f.datatype == F32 and f.count == 1 for f in msg.fields)
    assert msg.header.frame_id == "mocap" and msg.header.stamp.nanosec == 345
    assert msg.is_dense
    out, ids = read_points_xyz(msg)
    assert ids is None
    assert out.dtype == np.float64 and out.shape == (40, 3)
    np.testing.assert_array_equal(out, xyz.astype(np.float32).astype(np.float64))


def test_xyz_round_trip_with_ids():
    xyz = _xyz(25)
    ids = np.arange(100, 125)
    msg = make_xyz_cloud(xyz, ids=ids)
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("id", 12, U32)]
    assert msg.point_step == 16
    out, got = read_points_xyz(msg)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, ids)
    np.testing.assert_allclose(out, xyz, atol=1e-6)


def test_labeled_cloud_round_trip():
    xyz = _xyz(30)
    labels = np.arange(30, dtype=np.int32) - 1  # includes -1 (unlabeled)
    conf = np.linspace(0, 1, 30, dtype=np.float32)
    msg = make_labeled_cloud(xyz, labels, conf, header=Header(frame_id="w"))
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
        ("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("label", 12, I32), ("confidence", 16, F32)]
    assert msg.point_step == 20 and msg.header.frame_id == "w"
    arr = cloud_to_structured(msg)
    np.testing.assert_array_equal(arr["label"], labels)
    np.testing.assert_array_equal(arr["confidence"], conf)
    out, ids = read_points_xyz(msg)
    assert ids is None
    np.testing.assert_allclose(out, xyz, atol=1e-6)
    # scalar confidence broadcasts
    arr = cloud_to_structured(make_labeled_cloud(xyz, labels, 0.5))
    assert np.all(arr["confidence"] == 0.5)


def test_make_rejects_bad_shapes():
    with pytest.raises(PointCloudError, match=r"shape \(n, 3\)"):
        make_xyz_cloud(np.zeros((4, 2)))
    with pytest.raises(PointCloudError, match="ids"):
        make_xyz_cloud(np.zeros((4, 3)), ids=[1, 2, 3])
    with pytest.raises(PointCloudError, match="ids must be in"):
        make_xyz_cloud(np.zeros((2, 3)), ids=[-1, 2])
    with pytest.raises(PointCloudError, match="labels"):
        make_labeled_cloud(np.zeros((4, 3)), [0, 1], [1, 1, 1, 1])
    with pytest.raises(PointCloudError, match="confidence"):
        make_labeled_cloud(np.zeros((4, 3)), [0, 1, 2, 3], [1.0, 1.0])


def test_non_finite_values_are_returned_not_filtered():
    xyz = _xyz(5)
    xyz[1, 0] = np.nan
    xyz[3, 2] = np.inf
    msg = make_xyz_cloud(xyz)
    assert not msg.is_dense
    out, _ = read_points_xyz(msg)
    assert out.shape == (5, 3)
    assert np.isnan(out[1, 0]) and np.isposinf(out[3, 2])


def test_empty_cloud():
    msg = make_xyz_cloud(np.zeros((0, 3)))
    assert msg.width == 0 and len(msg.data) == 0
    out, ids = read_points_xyz(msg)
    assert out.shape == (0, 3) and out.dtype == np.float64 and ids is None
    msg = make_xyz_cloud(np.zeros((0, 3)), ids=np.zeros(0, np.uint32))
    out, ids = read_points_xyz(msg)
    assert out.shape == (0, 3) and ids.shape == (0,) and ids.dtype == np.int64
    # an organised cloud with height 0 / a hand-made empty message
    empty = build_cloud({"x": [], "y": [], "z": []},
                        [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8)], 12, 0, 7)
    assert read_points_xyz(empty)[0].shape == (0, 3)
    assert cloud_to_structured(make_labeled_cloud(np.zeros((0, 3)), [], [])).shape == (0,)


# --------------------------------------------------------------------------- foreign layouts

def test_arbitrary_field_order_and_point_padding():
    n = 12
    xyz = _xyz(n, 1)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
            "intensity": np.arange(n, dtype=np.float32), "ring": np.arange(n) % 16,
            "id": np.arange(n) * 3}
    layout = [("intensity", F32, 1, 0), ("z", F32, 1, 4), ("ring", U16, 1, 8),
              ("y", F32, 1, 12), ("id", U32, 1, 20), ("x", F32, 1, 28)]
    msg = build_cloud(cols, layout, point_step=40, height=1, width=n)
    out, ids = read_points_xyz(msg)
    np.testing.assert_allclose(out, xyz, atol=1e-6)
    np.testing.assert_array_equal(ids, cols["id"])
    arr = cloud_to_structured(msg)
    assert arr.dtype.names == ("intensity", "z", "ring", "y", "id", "x")
    np.testing.assert_array_equal(arr["ring"], cols["ring"])


@pytest.mark.parametrize("pad_last_row", [True, False])
def test_row_padding_and_height(pad_last_row):
    h, w = 4, 7
    xyz = _xyz(h * w, 2)
    layout = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8)]
    msg = build_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, layout, point_step=16,
                      height=h, width=w, row_pad=9, pad_last_row=pad_last_row)
    assert msg.row_step == w * 16 + 9
    out, _ = read_points_xyz(msg)
    assert out.shape == (h * w, 3)
    np.testing.assert_allclose(out, xyz, atol=1e-6)  # row-major order preserved


def test_height_without_row_padding_is_a_view():
    h, w = 3, 5
    xyz = _xyz(h * w, 3)
    layout = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8)]
    msg = build_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, layout, 12, h, w)
    arr = cloud_to_structured(msg)
    assert arr.shape == (h * w,)
    assert np.shares_memory(arr, np.frombuffer(msg.data, np.uint8))
    np.testing.assert_allclose(read_points_xyz(msg)[0], xyz, atol=1e-6)


@pytest.mark.parametrize("xyz_type", [F32, F64])
@pytest.mark.parametrize("id_type", [U32, I32])
def test_big_endian(xyz_type, id_type):
    n = 9
    xyz = _xyz(n, 4)
    ids = np.arange(n) + 70000
    size = DATATYPES[xyz_type].itemsize
    layout = [("x", xyz_type, 1, 0), ("y", xyz_type, 1, size), ("z", xyz_type, 1, 2 * size),
              ("id", id_type, 1, 3 * size)]
    msg = build_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "id": ids}, layout,
                      point_step=4 * size, height=1, width=n, row_pad=3, bigendian=True)
    # the bytes really are big-endian: the first x decodes as numpy '>f4'/'>f8'
    first = np.frombuffer(bytes(msg.data[:size]), ">f4" if size == 4 else ">f8")[0]
    assert first == pytest.approx(xyz[0, 0], abs=1e-6)
    out, got = read_points_xyz(msg)
    np.testing.assert_allclose(out, xyz, atol=1e-6 if size == 4 else 0)
    np.testing.assert_array_equal(got, ids)
    assert got.dtype == np.int64


def test_float64_xyz_exact():
    n = 10
    xyz = _xyz(n, 5) + 1e-9
    layout = [("x", F64, 1, 0), ("y", F64, 1, 8), ("z", F64, 1, 16)]
    msg = build_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, layout, 24, 1, n)
    out, _ = read_points_xyz(msg)
    np.testing.assert_array_equal(out, xyz)


@pytest.mark.parametrize("id_type", [U32, I32, U16, I8])
def test_id_integer_types(id_type):
    n = 6
    ids = np.array([0, 1, 2, 3, 5, 100])
    layout = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8), ("id", id_type, 1, 12)]
    msg = build_cloud({"x": 0, "y": 1, "z": 2, "id": ids}, layout, 16, 1, n)
    out, got = read_points_xyz(msg)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, ids)
    assert np.all(out == [0, 1, 2])


def test_count_greater_than_one_field():
    n = 4
    layout = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8), ("rgb", U8, 3, 12)]
    colors = np.arange(n * 3).reshape(n, 3)
    msg = build_cloud({"x": 1, "y": 2, "z": 3, "rgb": colors}, layout, 16, 1, n)
    arr = cloud_to_structured(msg)
    assert arr["rgb"].shape == (n, 3)
    np.testing.assert_array_equal(arr["rgb"], colors)
    assert read_points_xyz(msg)[0].shape == (n, 3)


def test_duck_typed_messages_from_rosbags():
    """Clouds deserialised by rosbags (data is an ndarray) read the same as rclpy ones."""
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    xyz = _xyz(50, 6)
    msg = make_xyz_cloud(xyz, ids=np.arange(50))
    bag_msg = ts.deserialize_cdr(serialize_message(msg), "sensor_msgs/msg/PointCloud2")
    assert isinstance(bag_msg.data, np.ndarray)
    out, ids = read_points_xyz(bag_msg)
    np.testing.assert_array_equal(out, read_points_xyz(msg)[0])
    np.testing.assert_array_equal(ids, np.arange(50))
    # plain bytes / lists as data work too
    ns = SimpleNamespace(**{k: getattr(msg, k) for k in
                            ("height", "width", "point_step", "row_step", "is_bigendian",
                             "fields")}, data=bytes(msg.data))
    np.testing.assert_array_equal(read_points_xyz(ns)[0], out)
    ns.data = list(msg.data)
    np.testing.assert_array_equal(read_points_xyz(ns)[0], out)


# ---------------------------------------------------------------------------------- errors

XYZ_LAYOUT = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8)]


def _cloud(layout=XYZ_LAYOUT, point_step=12, n=3, **kw):
    cols = {name: 1 for name, *_ in layout}
    return build_cloud(cols, layout, point_step, 1, n, **kw)


@pytest.mark.parametrize("missing", ["x", "y", "z"])
def test_missing_axis(missing):
    layout = [f for f in XYZ_LAYOUT if f[0] != missing]
    with pytest.raises(PointCloudError, match=rf"no '{missing}' field"):
        read_points_xyz(_cloud(layout))


@pytest.mark.parametrize("dtype", [I32, U16, U8])
def test_axis_with_wrong_datatype(dtype):
    layout = [("x", F32, 1, 0), ("y", dtype, 1, 4), ("z", F32, 1, 8)]
    with pytest.raises(PointCloudError, match=r"field 'y' has datatype \w+; x, y, z must be "
                                              r"FLOAT32 or FLOAT64"):
        read_points_xyz(_cloud(layout))


def test_axis_with_count_3():
    layout = [("x", F32, 3, 0), ("y", F32, 1, 12), ("z", F32, 1, 16)]
    with pytest.raises(PointCloudError, match="field 'x' has count 3"):
        read_points_xyz(_cloud(layout, point_step=20))


def test_id_minus_one_means_no_id_and_integral_float_ids():
    from dtm_labeler.ros.pointcloud import NO_ID, complete_ids
    layout = XYZ_LAYOUT + [("id", I32, 1, 12)]
    msg = build_cloud({"x": 0, "y": 0, "z": 0, "id": [3, -1, 4]}, layout, 16, 1, 3)
    ids = read_points_xyz(msg)[1]
    assert ids.tolist() == [3, NO_ID, 4] and complete_ids(ids) is None
    msg = build_cloud({"x": 0, "y": 0, "z": 0, "id": [3, 0xFFFFFFFF, 4]}, XYZ_LAYOUT + [("id", U32, 1, 12)],
                      16, 1, 3)
    assert read_points_xyz(msg)[1].tolist() == [3, NO_ID, 4]
    for ftype in (F32, F64):
        layout = XYZ_LAYOUT + [("id", ftype, 1, 16)]
        msg = build_cloud({"x": 0, "y": 0, "z": 0, "id": [7.0, -1.0, np.nan, 2.0 ** 24]}, layout, 24, 1, 4)
        assert read_points_xyz(msg)[1].tolist() == [7, NO_ID, NO_ID, 2 ** 24]
    full = read_points_xyz(build_cloud({"x": 0, "y": 0, "z": 0, "id": [5, 6]}, XYZ_LAYOUT + [("id", F32, 1, 12)],
                                       16, 1, 2))[1]
    assert complete_ids(full).tolist() == [5, 6]


def test_ids_that_cannot_be_read_are_rejected():
    layout = XYZ_LAYOUT + [("id", I32, 1, 12)]
    msg = build_cloud({"x": 0, "y": 0, "z": 0, "id": [3, -2, 4]}, layout, 16, 1, 3)
    with pytest.raises(PointCloudError, match="negative"):
        read_points_xyz(msg)
    layout = XYZ_LAYOUT + [("id", F32, 1, 12)]
    msg = build_cloud({"x": 0, "y": 0, "z": 0, "id": [3.0, 2.5, 4.0]}, layout, 16, 1, 3)
    with pytest.raises(PointCloudError, match="integral"):
        read_points_xyz(msg)
    layout = XYZ_LAYOUT + [("id", U32, 2, 12)]
    with pytest.raises(PointCloudError, match="count 2"):
        read_points_xyz(_cloud(layout, point_step=20))


def test_row_step_zero_padding_fields_and_empty_fields():
    """Layouts real drivers send: row_step left 0, PCL's '_' padding fields (several), a field
    of count 0, and an unrelated field of a datatype this reader does not know."""
    xyz = _xyz(5, 3).astype(np.float32)
    layout = [("x", F32, 1, 0), ("y", F32, 1, 4), ("z", F32, 1, 8), ("_", U8, 4, 12), ("_", U8, 4, 16),
              ("id", U32, 1, 20)]
    msg = build_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "_": 0, "id": np.arange(5)},
                      [f for f in layout if f[0] != "_"], 24, 1, 5)
    from sensor_msgs.msg import PointField
    msg.fields = [PointField(name=n, datatype=d, count=c, offset=o) for n, d, c, o in layout]
    msg.fields.append(PointField(name="intensity", datatype=F32, count=0, offset=24))
    msg.row_step = 0
    out, ids = read_points_xyz(msg)
    np.testing.assert_array_equal(out, xyz.astype(np.float64))
    assert ids.tolist() == list(range(5))
    assert cloud_to_structured(msg).dtype.names == ("x", "y", "z", "id")
    msg.fields.append(PointField(name="rgba", datatype=42, count=1, offset=12))
    assert read_points_xyz(msg)[0].shape == (5, 3)         # a field it does not need is not read
    with pytest.raises(PointCloudError, match="unknown PointField datatype 42"):
        cloud_to_structured(msg)                           # ... but the full decoder names it


def test_millimetre_clouds_are_recognised():
    from dtm_labeler.ros.pointcloud import looks_like_millimetres
    body = np.random.default_rng(0).uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 1.8], size=(14, 3))
    assert not looks_like_millimetres(body)
    assert not looks_like_millimetres(body + [40.0, -30.0, 0.0])     # far from the origin, in metres
    assert looks_like_millimetres(body * 1000.0)
    assert not looks_like_millimetres(np.array([[1500.0, 0, 0], [np.nan, 0, 0]]))


def test_data_length_mismatch():
    msg = _cloud(n=4)
    msg.data = array.array("B", bytes(msg.data)[:-5])
    with pytest.raises(PointCloudError, match=r"data has 43 bytes, expected .*48"):
        read_points_xyz(msg)
    msg = _cloud(n=4)
    msg.width = 5  # claims more points than the data holds (row_step left as is)
    msg.row_step = 60
    with pytest.raises(PointCloudError, match="data has 48 bytes"):
        cloud_to_structured(msg)


def test_layout_errors():
    msg = _cloud()
    msg.row_step = 20  # smaller than width*point_step = 36
    with pytest.raises(PointCloudError, match="row_step 20 is smaller"):
        read_points_xyz(msg)
    msg = _cloud()
    msg.fields[2].offset = 10  # z would end at byte 14 > point_step 12
    with pytest.raises(PointCloudError, match="field 'z' .* does not fit in point_step 12"):
        read_points_xyz(msg)
    msg = _cloud()
    msg.fields[2].datatype = 9
    with pytest.raises(PointCloudError, match="unknown PointField datatype 9"):
        cloud_to_structured(msg)
    msg = _cloud()
    msg.fields[1].name = "x"
    with pytest.raises(PointCloudError, match="duplicate field name 'x'"):
        cloud_to_structured(msg)
    msg = _cloud()
    msg.point_step = 0
    msg.row_step = 0
    with pytest.raises(PointCloudError):
        cloud_to_structured(msg)
    assert issubclass(PointCloudError, ValueError)


# ------------------------------------------------------------------------------ performance

def _median_us(fn, reps=200):
    fn()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e6


def test_ten_thousand_points_fast():
    n = 10_000
    xyz = _xyz(n, 7)
    msg = make_xyz_cloud(xyz, ids=np.arange(n))
    out, ids = read_points_xyz(msg)
    np.testing.assert_allclose(out, xyz, atol=1e-5)
    np.testing.assert_array_equal(ids, np.arange(n))
    decode = _median_us(lambda: read_points_xyz(msg))
    encode = _median_us(lambda: make_xyz_cloud(xyz, ids=np.arange(n)))
    print(f"\n10k points: decode {decode:.0f} us, encode {encode:.0f} us")
    assert decode < 1000, f"decoding 10,000 points took {decode:.0f} us (want well under 1 ms)"
    assert encode < 5000, f"encoding 10,000 points took {encode:.0f} us"


# ----------------------------------------------------------------------- property (hypothesis)

@st.composite
def layouts(draw):
    """Random PointCloud2 layouts: x, y, z (float32/64) + optional id + extra fields, any order,
    padding between fields, at point end and row end, any byte order, height >= 1."""
    fields = [(axis, draw(st.sampled_from([F32, F64])), 1) for axis in "xyz"]
    if draw(st.booleans()):
        fields.append(("id", draw(st.sampled_from([U8, U16, U32, I16, I32])), 1))
    for k in range(draw(st.integers(0, 3))):
        fields.append((f"extra{k}", draw(st.integers(1, 8)), draw(st.integers(1, 3))))
    fields = draw(st.permutations(fields))
    layout, offset = [], 0
    for name, dtype, count in fields:
        offset += draw(st.integers(0, 5))
        layout.append((name, dtype, count, offset))
        offset += DATATYPES[dtype].itemsize * count
    point_step = offset + draw(st.integers(0, 7))
    return (layout, point_step, draw(st.integers(1, 3)), draw(st.integers(0, 6)),
            draw(st.integers(0, 9)), draw(st.booleans()), draw(st.booleans()))


@settings(max_examples=80, deadline=None)
@given(spec=layouts(), seed=st.integers(0, 2**16))
def test_property_round_trip_random_layouts(spec, seed):
    layout, point_step, height, width, row_pad, bigendian, pad_last_row = spec
    n = height * width
    rng = np.random.default_rng(seed)
    cols = {}
    for name, dtype, count, _ in layout:
        shape = (n,) if count == 1 else (n, count)
        if name == "id" or DATATYPES[dtype].kind in "iu":
            info = np.iinfo(DATATYPES[dtype])
            cols[name] = rng.integers(max(info.min, 0), info.max, size=shape, endpoint=True)
        else:
            cols[name] = rng.normal(size=shape).astype(DATATYPES[dtype])
    msg = build_cloud(cols, layout, point_step, height, width, row_pad, bigendian, pad_last_row)
    out, ids = read_points_xyz(msg)
    assert out.shape == (n, 3)
    for i, axis in enumerate("xyz"):
        np.testing.assert_array_equal(out[:, i], cols[axis].astype(np.float64))
    if "id" in cols:
        np.testing.assert_array_equal(ids, cols["id"])
    else:
        assert ids is None
    arr = cloud_to_structured(msg)
    for name, *_ in layout:
        np.testing.assert_array_equal(arr[name], cols[name])
