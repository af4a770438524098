#!/usr/bin/env python3
"""The Python module (python/pillarseg) over the built libpillarseg.so: its labels and
probabilities are `pillarseg infer`'s for the same scan and checkpoint; probabilities sum to 1
with their arg-max the labels; (N, 3), float64 and strided points give the (N, 4) float32 result,
and an (N, 4) float32 C-contiguous array goes in unconverted; the input settings (reflectance,
transform) act as the same change made to the points; bad arguments and files raise with the
library's message; a closed segmenter raises; read_points reads back a .bin file (and the real
scan of ../shared when present); examples/segment_scan.py runs.

The model is the fuzz corpus's tiny trained checkpoint (32 x 16 cells of 0.4 m), so every call
is cheap.

Usage: test_pillarseg.py PILLARSEG_BINARY WORK_DIR, with PILLARSEG_LIBRARY and PYTHONPATH set
(tests/CMakeLists.txt). Exits 77 (CTest's skip) where numpy is not installed.
"""

import ctypes.util
import os
import re
import shutil
import subprocess
import sys
import threading
import unittest
from pathlib import Path

try:
    import numpy as np
except ImportError:
    print(f"test_pillarseg: skipped: numpy is not installed for {sys.executable} "
          "(Debian: apt-get install python3-numpy)")
    sys.exit(77)

import pillarseg

ROOT = Path(__file__).resolve().parents[2]
WEIGHTS = ROOT / "fuzz" / "corpus" / "checkpoint" / "trained.safetensors"
REAL_SCAN = Path(os.environ.get("PILLARSEG_SHARED_DATA", ROOT.parent / "shared" / "data")) / \
    "semantickitti" / "sequences" / "99" / "velodyne" / "000000.bin"
PILLARSEG_BINARY = None
WORK = None


def random_scan(count, seed):
    """count points over the tiny model's grid (x in +-6.4 m, y in +-3.2 m), reflectance in [0, 1)."""
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-6.0, 6.0, count), rng.uniform(-3.0, 3.0, count),
                     rng.uniform(-1.8, 0.8, count), rng.uniform(0.0, 1.0, count)], axis=1).astype(np.float32)


def infer(scan_path, name, *options):
    """pillarseg infer's (labels, probabilities) for one scan file on the CPU."""
    prefix = WORK / name
    subprocess.run([str(PILLARSEG_BINARY), "--threads", "2", "infer", "--weights", str(WEIGHTS), "--scan",
                    str(scan_path), "--out", str(prefix), "--probabilities", "--no-png", *options],
                   check=True, stdout=subprocess.DEVNULL)
    labels = np.fromfile(f"{prefix}.u8", dtype=np.uint8)
    probabilities = np.fromfile(f"{prefix}.f16", dtype=np.float16).astype(np.float32)
    return labels, probabilities


class SegmenterTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.segmenter = pillarseg.Segmenter(WEIGHTS, threads=2)
        cls.points = random_scan(3000, seed=5)

    @classmethod
    def tearDownClass(cls):
        cls.segmenter.close()

    def test_grid_and_names(self):
        s = self.segmenter
        self.assertEqual(s.grid, (16, 32))
        self.assertEqual(s.geometry, pillarseg.Geometry(-6.4, -3.2, 0.4))
        self.assertEqual(s.device_name, "cpu")
        self.assertEqual(s.precision, "fp32")
        self.assertIn("16 x 32 cells", repr(s))
        self.assertEqual(len(pillarseg.class_names), pillarseg.NUM_CLASSES + 1)
        self.assertEqual((pillarseg.class_names[0], pillarseg.class_names[1], pillarseg.class_names[12]),
                         ("unlabeled", "vehicle", "terrain"))

    def test_versions_agree(self):
        pyproject = (ROOT / "python" / "pyproject.toml").read_text()
        self.assertEqual(re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1), pillarseg.__version__)
        self.assertEqual(pillarseg.library_version, pillarseg.__version__,
                         "the library's version differs from the module's (python/pillarseg/__init__.py, "
                         "python/pyproject.toml)")

    def test_labels_and_probabilities_are_infer_s(self):
        scan = WORK / "random.bin"
        self.points.tofile(scan)
        labels, probabilities = self.segmenter.segment(self.points, probabilities=True)
        self.assertEqual((labels.shape, labels.dtype), ((16, 32), np.uint8))
        self.assertEqual((probabilities.shape, probabilities.dtype), ((12, 16, 32), np.float32))
        expected_labels, expected_probabilities = infer(scan, "random")
        np.testing.assert_array_equal(labels.ravel(), expected_labels)
        # .f16 holds the probabilities rounded to float16: half an ulp is 2^-12 below 1.
        np.testing.assert_allclose(probabilities.ravel(), expected_probabilities, rtol=0, atol=2.5e-4)
        np.testing.assert_array_equal(self.segmenter.segment(self.points), labels)

    def test_probabilities_sum_to_one_and_their_argmax_is_the_labels(self):
        labels, probabilities = self.segmenter.segment(self.points, probabilities=True)
        np.testing.assert_allclose(probabilities.sum(axis=0), 1.0, atol=1e-5)
        self.assertTrue(((probabilities >= 0) & (probabilities <= 1)).all())
        np.testing.assert_array_equal(probabilities.argmax(axis=0) + 1, labels)
        self.assertGreater(len(np.unique(labels)), 1, "a map of one class tests little")

    def test_emulated_cuda_backend_agrees(self):
        with pillarseg.Segmenter(WEIGHTS, device="emu", threads=2) as emu:
            self.assertTrue(emu.device_name.startswith("emu:0"), emu.device_name)
            labels, probabilities = emu.segment(self.points, probabilities=True)
        expected_labels, expected_probabilities = self.segmenter.segment(self.points, probabilities=True)
        np.testing.assert_array_equal(labels, expected_labels)
        np.testing.assert_allclose(probabilities, expected_probabilities, rtol=0, atol=1e-5)

    def test_masked_cells_are_unlabeled_with_zero_probabilities(self):
        with pillarseg.Segmenter(WEIGHTS, threads=2, mask_unobserved=True) as masked:
            labels, probabilities = masked.segment(self.points[:40], probabilities=True)
        unobserved = labels == 0
        self.assertTrue(unobserved.any() and not unobserved.all())
        self.assertTrue((probabilities[:, unobserved] == 0).all())
        np.testing.assert_array_equal(labels[~unobserved], self.segmenter.segment(self.points[:40])[~unobserved])

    def test_points_are_passed_in_place_or_converted_once(self):
        self.assertIs(pillarseg.as_points(self.points), self.points)
        strided = np.repeat(self.points, 2, axis=0)[::2]
        self.assertFalse(strided.flags.c_contiguous)
        self.assertIsNot(pillarseg.as_points(strided), strided)
        as_float64 = np.asfortranarray(self.points.astype(np.float64))
        expected = self.segmenter.segment(self.points)
        np.testing.assert_array_equal(self.segmenter.segment(strided), expected)
        np.testing.assert_array_equal(self.segmenter.segment(as_float64), expected)
        np.testing.assert_array_equal(self.segmenter.segment(self.points.tolist()), expected)

    def test_three_columns_mean_reflectance_zero(self):
        no_reflectance = self.points.copy()
        no_reflectance[:, 3] = 0
        np.testing.assert_array_equal(pillarseg.as_points(self.points[:, :3]), no_reflectance)
        np.testing.assert_array_equal(self.segmenter.segment(self.points[:, :3]),
                                      self.segmenter.segment(no_reflectance))

    def test_no_points(self):
        labels = self.segmenter.segment(np.zeros((0, 4), dtype=np.float32))
        self.assertEqual(labels.shape, (16, 32))

    def test_bad_points(self):
        with self.assertRaisesRegex(ValueError, r"points: expected an \(N, 4\).*got shape \(10, 5\)"):
            self.segmenter.segment(np.zeros((10, 5), dtype=np.float32))
        with self.assertRaisesRegex(ValueError, r"got shape \(4,\)"):
            self.segmenter.segment(np.zeros(4, dtype=np.float32))
        with self.assertRaisesRegex(TypeError, "points: expected real numbers, got dtype complex"):
            self.segmenter.segment(np.zeros((3, 4), dtype=np.complex64))

    def test_threads_share_one_segmenter(self):
        expected = self.segmenter.segment(self.points)
        results = []

        def run():
            results.extend(self.segmenter.segment(self.points) for _ in range(3))

        workers = [threading.Thread(target=run) for _ in range(2)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        self.assertEqual(len(results), 6)
        for labels in results:
            np.testing.assert_array_equal(labels, expected)


class InputSettingsTest(unittest.TestCase):
    """Each input setting gives the labels of the same change made to the points by hand."""

    @classmethod
    def setUpClass(cls):
        cls.plain = pillarseg.Segmenter(WEIGHTS, threads=2)
        cls.points = random_scan(3000, seed=9)
        cls.points[:, 3] *= 0.4

    @classmethod
    def tearDownClass(cls):
        cls.plain.close()

    def check(self, expected_points, **settings):
        with pillarseg.Segmenter(WEIGHTS, threads=2, **settings) as s:
            labels, probabilities = s.segment(self.points, probabilities=True)
        expected_labels, expected_probabilities = self.plain.segment(expected_points, probabilities=True)
        np.testing.assert_array_equal(labels, expected_labels)
        np.testing.assert_array_equal(probabilities, expected_probabilities)

    def test_no_reflectance(self):
        zero = self.points.copy()
        zero[:, 3] = 0
        self.check(zero, reflectance="none")
        _, with_reflectance = self.plain.segment(self.points, probabilities=True)
        _, without = self.plain.segment(zero, probabilities=True)
        self.assertFalse(np.array_equal(with_reflectance, without), "reflectance made no difference")

    def test_reflectance_scale_and_offset(self):
        # r in [0, 0.4): 2 r + 0.125 in [0.125, 0.925), inside the clip; both steps exact in float32.
        scaled = self.points.copy()
        scaled[:, 3] = 2 * scaled[:, 3] + np.float32(0.125)
        self.check(scaled, reflectance={"scale": 2.0, "offset": 0.125, "clip": False})
        self.check(scaled, reflectance={"scale": 2.0, "offset": 0.125})

    def test_reflectance_clip(self):
        # 4 r - 0.5 spans [-0.5, 1.1): clipped to [0, 1] it is what the plain segmenter gets.
        stretched = self.points.copy()
        stretched[:, 3] = np.clip(4 * stretched[:, 3] - np.float32(0.5), 0, 1)
        self.check(stretched, reflectance={"scale": 4.0, "offset": -0.5, "clip": True})

    def test_transform(self):
        # A quarter turn about z: (x, y, z) -> (-y, x, z), exact in float32.
        quarter_turn = [[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
        turned = self.points.copy()
        turned[:, 0], turned[:, 1] = -self.points[:, 1], self.points[:, 0]
        self.check(turned, transform=quarter_turn)
        self.check(self.points, transform=np.eye(4))

    def test_flips(self):
        # The probabilities of 4 flips: the plain segmenter's over the scan mirrored y -> -y, x -> -x
        # and both, each mirrored back, summed in that order and scaled (the library's operations:
        # the same bits); the labels their arg-max; infer --flips 4 the same labels.
        total = np.zeros((12, 16, 32), dtype=np.float32)
        for copy in range(4):
            mirrored = self.points.copy()
            if copy & 1:
                mirrored[:, 1] = -mirrored[:, 1]
            if copy & 2:
                mirrored[:, 0] = -mirrored[:, 0]
            _, p = self.plain.segment(mirrored, probabilities=True)
            if copy & 1:
                p = p[:, ::-1, :]
            if copy & 2:
                p = p[:, :, ::-1]
            total += p
        with pillarseg.Segmenter(WEIGHTS, threads=2, flips=4) as s:
            labels, probabilities = s.segment(self.points, probabilities=True)
        np.testing.assert_array_equal(probabilities, total * np.float32(0.25))
        np.testing.assert_array_equal(labels, probabilities.argmax(axis=0) + 1)
        _, one = self.plain.segment(self.points, probabilities=True)
        self.assertFalse(np.array_equal(probabilities, one), "the mirrored copies changed nothing")
        scan = WORK / "flips.bin"
        self.points.tofile(scan)
        expected_labels, _ = infer(scan, "flips", "--flips", "4")
        np.testing.assert_array_equal(labels.ravel(), expected_labels)
        with self.assertRaisesRegex(pillarseg.Error, "options->flips must be 1 .* got 3"):
            pillarseg.Segmenter(WEIGHTS, flips=3)

    def test_bad_settings(self):
        with self.assertRaisesRegex(ValueError, r"transform: expected a 4 x 4 matrix, got shape \(3, 3\)"):
            pillarseg.Segmenter(WEIGHTS, transform=np.eye(3))
        with self.assertRaisesRegex(ValueError, "transform: every entry must be finite"):
            pillarseg.Segmenter(WEIGHTS, transform=np.diag([1.0, 1.0, np.nan, 1.0]))
        with self.assertRaisesRegex(ValueError, "reflectance: expected None, \"none\" or a dict"):
            pillarseg.Segmenter(WEIGHTS, reflectance="off")
        with self.assertRaisesRegex(ValueError, r"reflectance: unknown keys \['gain'\]"):
            pillarseg.Segmenter(WEIGHTS, reflectance={"gain": 2.0})
        with self.assertRaisesRegex(TypeError, "threads must be an int"):
            pillarseg.Segmenter(WEIGHTS, threads=1.5)


class ErrorsAndLifetimeTest(unittest.TestCase):
    def test_bad_weights_path_names_it(self):
        missing = WORK / "no such model.safetensors"
        with self.assertRaises(pillarseg.Error) as raised:
            pillarseg.Segmenter(missing)
        self.assertIn(str(missing), str(raised.exception))
        self.assertIn("pillarseg_open", str(raised.exception))
        self.assertIsInstance(raised.exception, RuntimeError)

    def test_library_not_loaded_says_what_was_tried(self):
        def import_error(library):
            run = subprocess.run([sys.executable, "-c", "import pillarseg"], capture_output=True, text=True,
                                 env={**os.environ, "PILLARSEG_LIBRARY": library})
            self.assertNotEqual(run.returncode, 0)
            return run.stderr

        missing = str(WORK / "libpillarseg.so.0")
        self.assertIn(f"no libpillarseg could be loaded (set PILLARSEG_LIBRARY to its path); tried\n"
                      f"  $PILLARSEG_LIBRARY: {missing}: cannot open shared object file", import_error(missing))
        libm = ctypes.util.find_library("m")
        self.assertIn(f"{libm} ($PILLARSEG_LIBRARY) has no pillarseg_version: it is not libpillarseg",
                      import_error(libm))

    def test_bad_options_are_the_library_s_errors(self):
        with self.assertRaisesRegex(pillarseg.Error, "options->device must be"):
            pillarseg.Segmenter(WEIGHTS, device="tpu")
        with self.assertRaisesRegex(pillarseg.Error, "options->precision"):
            pillarseg.Segmenter(WEIGHTS, precision="int4")
        with self.assertRaisesRegex(pillarseg.Error, "precision int8: no input scale .*pillarseg calibrate"):
            pillarseg.Segmenter(WEIGHTS, precision="int8")
        with self.assertRaisesRegex(pillarseg.Error, "options->threads must be >= 0"):
            pillarseg.Segmenter(WEIGHTS, threads=-1)

    def test_config_grid_wins(self):
        config = WORK / "fine_grid.yaml"
        config.write_text("grid: {x: [-6.4, 6.4], y: [-3.2, 3.2], z: [-2.5, 1.5], cell: 0.2, voxel_z: 0.5}\n"
                          "model: {max_points_per_pillar: 8, pillar_channels: 4, occupancy: 2d, "
                          "occupancy_channels: 2, base_width: 4, depth: 2}\n")
        with pillarseg.Segmenter(WEIGHTS, config=config, threads=2) as s:
            self.assertEqual(s.grid, (32, 64))
            self.assertEqual(s.geometry.cell, 0.2)
            self.assertEqual(s.segment(random_scan(500, seed=1)).shape, (32, 64))

    def test_closed_segmenter_raises_and_context_manager_closes(self):
        with pillarseg.Segmenter(WEIGHTS, threads=1) as s:
            self.assertFalse(s.closed)
        self.assertTrue(s.closed)
        self.assertIn("(closed)", repr(s))
        for use in (lambda: s.segment(random_scan(10, seed=2)), lambda: s.grid, lambda: s.device_name):
            with self.assertRaisesRegex(pillarseg.Error, "the segmenter of .*trained.safetensors is closed"):
                use()
        s.close()
        with self.assertRaises(pillarseg.Error):
            with s:
                pass


class ReadPointsTest(unittest.TestCase):
    def test_bin_read_back_without_its_non_finite_points(self):
        points = random_scan(1234, seed=3)
        points[0] = [-0.0, 1e-30, 3.0e38, -1.0]
        written = points.copy()
        written[7] = [np.nan, 1.0, 2.0, 0.5]
        written[9] = [1.0, 2.0, 3.0, np.inf]
        path = WORK / "round_trip.bin"
        written.tofile(path)
        read = pillarseg.read_points(path)
        self.assertEqual((read.shape, read.dtype, read.flags.c_contiguous), ((1232, 4), np.float32, True))
        kept = np.delete(points, [7, 9], axis=0)
        np.testing.assert_array_equal(read.view(np.uint32), kept.view(np.uint32))
        np.testing.assert_array_equal(pillarseg.read_points(str(path), format="kitti"), read)
        with self.assertRaisesRegex(pillarseg.Error, "format"):
            pillarseg.read_points(path, format="las")

    def test_empty_bin(self):
        path = WORK / "empty.bin"
        path.write_bytes(b"")
        self.assertEqual(pillarseg.read_points(path).shape, (0, 4))

    def test_errors_name_the_file(self):
        path = WORK / "truncated.bin"
        path.write_bytes(b"\0" * 17)
        with self.assertRaisesRegex(pillarseg.Error, re.escape(str(path))):
            pillarseg.read_points(path)
        missing = WORK / "missing.bin"
        with self.assertRaisesRegex(pillarseg.Error, re.escape(str(missing))):
            pillarseg.read_points(missing)

    @unittest.skipUnless(REAL_SCAN.exists(), f"the real scan {REAL_SCAN} is not here")
    def test_real_scan_read_and_segmented_as_infer_does(self):
        points = pillarseg.read_points(REAL_SCAN)
        np.testing.assert_array_equal(points, np.fromfile(REAL_SCAN, dtype=np.float32).reshape(-1, 4))
        with pillarseg.Segmenter(WEIGHTS, threads=2) as s:
            labels = s.segment(points)
        expected_labels, _ = infer(REAL_SCAN, "real")
        np.testing.assert_array_equal(labels.ravel(), expected_labels)


class ExampleTest(unittest.TestCase):
    def test_segment_scan_example(self):
        scan = WORK / "example.bin"
        points = random_scan(2000, seed=4)
        points.tofile(scan)
        out = WORK / "example_labels"
        run = subprocess.run([sys.executable, str(ROOT / "examples" / "segment_scan.py"), str(WEIGHTS), str(scan),
                              str(out)], check=True, capture_output=True, text=True)
        with pillarseg.Segmenter(WEIGHTS) as s:
            labels = s.segment(points)
        counts = np.bincount(labels.ravel(), minlength=pillarseg.NUM_CLASSES + 1)
        top = int(counts.argmax())
        self.assertIn(f"{pillarseg.class_names[top]:>12} {counts[top]:6d}", run.stdout)
        if Path(f"{out}.npy").exists():
            np.testing.assert_array_equal(np.load(f"{out}.npy"), labels)
        else:
            from PIL import Image
            np.testing.assert_array_equal(np.asarray(Image.open(f"{out}.png")), labels)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    PILLARSEG_BINARY = Path(sys.argv[1])
    WORK = Path(sys.argv[2])
    shutil.rmtree(WORK, ignore_errors=True)
    WORK.mkdir(parents=True)
    unittest.main(argv=[sys.argv[0], *sys.argv[3:]], verbosity=2)
