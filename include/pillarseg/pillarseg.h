/* pillarseg: a dense top-view semantic grid map from one LiDAR sweep (PillarSegNet,
 * Fei et al., IV 2021). The C API: a stable ABI for C, C++, Python ctypes, Rust and ROS nodes.
 *
 *   pillarseg_options options;
 *   pillarseg_default_options(&options);
 *   options.device = "cuda";
 *   char error[512];
 *   pillarseg_segmenter* s = pillarseg_open("model.safetensors", NULL, &options, error, sizeof error);
 *   if (!s) { fprintf(stderr, "%s\n", error); return 1; }
 *   int width, height;
 *   pillarseg_grid(s, &width, &height);
 *   uint8_t* labels = malloc((size_t)width * height);
 *   if (pillarseg_segment(s, points, num_points, labels, NULL, error, sizeof error) != 0) ...
 *   pillarseg_close(s);
 *
 * Points are float32 records x, y, z, reflectance (16 bytes, as in a SemanticKITTI .bin file) in
 * the sensor's frame, metres. The map is `height` rows of `width` cells: row iy, column ix, cell
 * (ix, iy) covering x in [x_min + ix cell, x_min + (ix + 1) cell), likewise y; class ids
 * 1..PILLARSEG_NUM_CLASSES (0: unlabeled, where mask_unobserved hides a cell no ray observed),
 * named by pillarseg_class_name. This is what `pillarseg infer` writes as PREFIX.u8.
 *
 * Errors: a function that can fail returns NULL or non-zero and writes one line saying what was
 * wrong into the caller's `error` buffer (truncated to error_size - 1 bytes, always terminated;
 * error may be NULL). No C++ exception, abort or exit crosses this interface.
 *
 * Threads: a segmenter is used by one thread at a time (calls on one segmenter from several
 * threads must be serialised by the caller); different segmenters may be used at the same time
 * from different threads, each with its own device memory and CUDA stream. pillarseg_version,
 * pillarseg_default_options and pillarseg_class_name may be called from any thread at any time.
 *
 * Memory: pillarseg_open plans and allocates; after the first few scans (and once a scan with
 * more points than any before has been seen) pillarseg_segment allocates nothing.
 */
#ifndef PILLARSEG_PILLARSEG_H
#define PILLARSEG_PILLARSEG_H

#include <stddef.h>
#include <stdint.h>

#if defined(_WIN32)
#define PILLARSEG_API
#else
#define PILLARSEG_API __attribute__((visibility("default")))
#endif

#ifdef __cplusplus
extern "C" {
#endif

#define PILLARSEG_VERSION_MAJOR 0
#define PILLARSEG_VERSION_MINOR 5
#define PILLARSEG_VERSION_PATCH 0

/* Classes of the map: 1 vehicle, 2 person, 3 two-wheel, 4 rider, 5 road, 6 sidewalk,
 * 7 other-ground, 8 building, 9 object, 10 vegetation, 11 trunk, 12 terrain; 0 unlabeled. */
#define PILLARSEG_NUM_CLASSES 12

typedef struct pillarseg_segmenter pillarseg_segmenter;

/* Set by pillarseg_default_options; change the fields you need. struct_size lets a later version
 * add fields at the end: a program built against this header passes its own size. */
typedef struct pillarseg_options {
  size_t struct_size;       /* sizeof(pillarseg_options) */
  const char* device;       /* "cpu" (default), "cuda" (a GPU), "emu" (the CUDA backend on the
                               CPU emulation: slow, for verification) */
  int threads;              /* CPU threads of this segmenter's work, 0 = all hardware threads */
  int cuda_device;          /* CUDA device ordinal with "cuda" (default 0) */
  int mask_unobserved;      /* non-zero: cells no ray observed get class 0 and probabilities 0 */
  const char* convolution;  /* Conv2d with "cuda": "own" (default), "cudnn" or "cublas" */
  const char* precision;    /* the convolutions: "fp32" (default), "bf16" or "fp16" (tensor cores
                               with "cuda" on compute capability 8.0+, or "emu"; elsewhere fp32
                               runs, see pillarseg_precision), or "int8" (the U-Net on INT8: weights
                               calibrated by `pillarseg calibrate`, required everywhere; CPUs with
                               AVX512-VNNI, "cuda" 8.0+, "emu"; elsewhere fp32 runs) */
  /* The sensor's points into the model's frame and scale (docs/formats.md), applied by
     pillarseg_segment before anything else; the identity (the defaults) leaves the points as given,
     and then a run config's input: section (config_path) applies. */
  int reflectance_none;       /* non-zero: the sensor gives no reflectance; every point gets 0 */
  float reflectance_scale;    /* reflectance = clip(scale * r + offset) (default 1) */
  float reflectance_offset;   /* (default 0) */
  int reflectance_clip;       /* non-zero: clamp to [0, 1] (default 1) */
  double transform[16];       /* row-major 4x4 from the sensor's frame into the model's
                                 (identity by default) */
  /* Since 0.5: test-time mirrors. The softmax averaged over 1 (default: the scan alone), 2 (and
     its mirror y -> -y) or 4 (and x -> -x, and both) copies of the scan, the labels its arg-max:
     that many passes of the network; the grid must be symmetric about the sensor. */
  int flips;
} pillarseg_options;

/* "0.5.0": the library's version (the header's is PILLARSEG_VERSION_*). */
PILLARSEG_API const char* pillarseg_version(void);

/* Fills the first struct_size bytes of *options with the defaults and sets options->struct_size
 * to struct_size (at most this library's sizeof(pillarseg_options)): device "cpu", threads 0,
 * cuda_device 0, mask_unobserved 0, convolution "own", precision "fp32", reflectance_none 0,
 * reflectance_scale 1, reflectance_offset 0, reflectance_clip 1, transform the identity, flips 1. With
 * scale 1 and offset 0 the reflectance is passed as stored (clip applies to a scaled or offset
 * one). Nothing past struct_size is written, so a program built against an older header, whose
 * struct is shorter, is safe with a newer library. Call it through pillarseg_default_options. */
PILLARSEG_API void pillarseg_init_options(pillarseg_options* options, size_t struct_size);

/* The defaults in a struct of this header's size: pillarseg_init_options(options, sizeof
 * *options), as zlib's deflateInit passes sizeof(z_stream). (The library also exports a function
 * of this name, for programs built against version 0.3: it fills 0.3's struct, the members up to
 * `precision`.) */
PILLARSEG_API void pillarseg_default_options(pillarseg_options* options);
#define pillarseg_default_options(options) pillarseg_init_options((options), sizeof(*(options)))

/* Opens a segmenter on `weights_path`, a safetensors checkpoint: one written by `pillarseg
 * train`, or a weights-only file (for example exported from PyTorch with the authors' module
 * names), whose architecture follows from its tensor shapes and whose grid is the paper's
 * (100 m x 50 m at 0.1 m: 1000 x 500 cells). config_path (may be NULL) is a run config YAML
 * whose grid: and model: settings then win. options may be NULL (the defaults). Returns NULL on
 * failure, with the reason in `error`. */
PILLARSEG_API pillarseg_segmenter* pillarseg_open(const char* weights_path, const char* config_path,
                                                  const pillarseg_options* options, char* error,
                                                  size_t error_size);

/* The map's size in cells: width along x (columns), height along y (rows). */
PILLARSEG_API void pillarseg_grid(const pillarseg_segmenter* s, int* width, int* height);

/* The map's placement: cell (ix, iy) covers x in [x_min + ix cell, x_min + (ix + 1) cell) and
 * y in [y_min + iy cell, ...), metres in the points' frame; any pointer may be NULL. */
PILLARSEG_API void pillarseg_grid_geometry(const pillarseg_segmenter* s, double* x_min, double* y_min,
                                           double* cell);

/* The device the segmenter runs on, e.g. "cpu" or "cuda:0 (NVIDIA H200)"; valid until close. */
PILLARSEG_API const char* pillarseg_device_name(const pillarseg_segmenter* s);

/* The arithmetic the segmenter's convolutions run in: "fp32", "bf16" or "fp16" (fp32 where the
 * options asked for bf16 or fp16 on a device without them). */
PILLARSEG_API const char* pillarseg_precision(const pillarseg_segmenter* s);

/* "vehicle" ... "terrain" for ids 1..12, "unlabeled" for 0, NULL for any other id. */
PILLARSEG_API const char* pillarseg_class_name(int class_id);

/* Segments one sweep: points_xyzr holds num_points records (x, y, z, reflectance), any number
 * including 0; points with a non-finite value (coordinate or reflectance) are ignored. Writes
 * labels (height x width bytes, class ids) and, when probabilities is not NULL, the softmax
 * probabilities (PILLARSEG_NUM_CLASSES x height x width floats, class k - 1 in plane k - 1).
 * Returns 0 on success; else non-zero with the reason in `error`, and the outputs unspecified. */
PILLARSEG_API int pillarseg_segment(pillarseg_segmenter* s, const float* points_xyzr, size_t num_points,
                                    uint8_t* labels, float* probabilities, char* error,
                                    size_t error_size);

/* Frees the segmenter and its device memory; NULL is ignored. */
PILLARSEG_API void pillarseg_close(pillarseg_segmenter* s);

/* Reads a point file (KITTI .bin, .pcd, .ply, .npy, nuScenes .pcd.bin) into a new array of
   num_points x 4 float32 (x, y, z, reflectance as stored; no mapping applied); format NULL:
   by extension, else "kitti", "pcd", "ply", "npy", "nuscenes". Free it with pillarseg_free.
   Returns 0, or non-zero with the reason in error (and *points_xyzr NULL). Points with a
   non-finite value are left out. */
PILLARSEG_API int pillarseg_read_points(const char* path, const char* format,
                                       float** points_xyzr, size_t* num_points,
                                       char* error, size_t error_size);
PILLARSEG_API void pillarseg_free(void* memory);

#ifdef __cplusplus
}
#endif

#endif /* PILLARSEG_PILLARSEG_H */
