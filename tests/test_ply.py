import numpy as np
import pytest
from raster_scenes import random_scene

import ghsplat_jax as gs
from ghsplat_jax.data.ply import is_3dgs_file, read_vertices


def test_round_trip_is_bit_exact(tmp_path):
    s = random_scene(57, degree=3)
    path = gs.save_ply(s, tmp_path / "a.ply")
    back = gs.load_ply(path)
    for f in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"):
        assert np.array_equal(np.asarray(getattr(s, f)), getattr(back, f)), f
    names = read_vertices(path).dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert names[-7:] == ("opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3")
    # f_rest is channel-major: the first 15 entries are red.
    v = read_vertices(path)
    assert np.array_equal(v["f_rest_1"], np.asarray(s.sh_rest)[:, 1, 0])
    assert np.array_equal(v["f_rest_15"], np.asarray(s.sh_rest)[:, 0, 1])


def test_viewer_variant_and_3dgs_files(tmp_path):
    s = random_scene(10)
    path = gs.save_ply(s, tmp_path / "viewer.ply", viewer_compatible=True)
    assert is_3dgs_file(path)
    assert np.allclose(read_vertices(path)["scale_2"], np.log(1e-6))
    with pytest.warns(UserWarning, match="largest two"):
        back = gs.load_ply(path)
    np.testing.assert_array_equal(np.sort(back.log_scales, 1), np.sort(np.asarray(s.log_scales), 1))


@pytest.mark.parametrize("content, message", [
    (b"hello world\n", "not a PLY"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n", "truncated header"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n" + bytes(12),
     "missing properties"),
])
def test_malformed_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(gs.PlyError, match=message) as info:
        gs.load_ply(path)
    assert "bad.ply" in str(info.value)


def test_truncated_data_and_missing_file(tmp_path):
    path = gs.save_ply(random_scene(20), tmp_path / "t.ply")
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(gs.PlyError, match="truncated"):
        gs.load_ply(path)
    with pytest.raises(gs.PlyError, match="no such file"):
        gs.load_ply(tmp_path / "nope.ply")


def test_refuses_to_write_nan(tmp_path):
    s = random_scene(5)
    bad = gs.Surfels(np.asarray(s.means).copy(), s.quats, s.log_scales, s.opacity_logits, s.sh_dc, s.sh_rest)
    bad.means[2, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        gs.save_ply(bad, tmp_path / "n.ply")
    assert not list(tmp_path.iterdir())


def test_3dgs_gaussian_keeps_its_plane():
    """A 3DGS Gaussian whose smallest axis is x or y becomes a surfel in the plane of the other two."""
    from ghsplat_jax.core.quaternions import to_rotation_matrix
    from ghsplat_jax.data.ply import surfel_from_3dgs

    r = np.random.default_rng(0)
    q = r.normal(size=(3, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales3 = np.log(np.array([[0.001, 0.2, 0.3], [0.2, 0.001, 0.3], [0.3, 0.2, 0.001]]))
    s2, q2 = surfel_from_3dgs(scales3, q)
    R, R2 = np.asarray(to_rotation_matrix(q)), np.asarray(to_rotation_matrix(q2))
    for i, dropped in enumerate([0, 1, 2]):
        kept = [a for a in range(3) if a != dropped]
        np.testing.assert_allclose(s2[i], scales3[i, kept], rtol=1e-6)
        # Tangent axes are the kept axes (up to sign); the normal is the dropped axis.
        for j, axis in enumerate(kept):
            assert abs(abs(R2[i, :, j] @ R[i, :, axis]) - 1) < 1e-5
        assert abs(abs(R2[i, :, 2] @ R[i, :, dropped]) - 1) < 1e-5
