/* Segments one SemanticKITTI scan with the C API: segment_scan_c WEIGHTS SCAN.bin OUT.u8 [DEVICE]
 * writes the label map (height rows of width class ids, as `pillarseg infer` writes PREFIX.u8)
 * and prints how many cells each class got. DEVICE: cpu (default), cuda or emu. */
#include <pillarseg/pillarseg.h>
#include <stdio.h>
#include <stdlib.h>

static float* read_points(const char* path, size_t* count) {
  FILE* file = fopen(path, "rb");
  if (!file) return NULL;
  fseek(file, 0, SEEK_END);
  const long bytes = ftell(file);
  fseek(file, 0, SEEK_SET);
  float* points = malloc(bytes > 0 ? (size_t)bytes : 1);
  *count = bytes > 0 ? (size_t)bytes / 16 : 0;
  if (points && fread(points, 16, *count, file) != *count) {
    free(points);
    points = NULL;
  }
  fclose(file);
  return points;
}

int main(int argc, char** argv) {
  if (argc < 4) {
    fprintf(stderr, "usage: %s WEIGHTS.safetensors SCAN.bin OUT.u8 [cpu|cuda|emu]\n", argv[0]);
    return 2;
  }
  size_t num_points = 0;
  float* points = read_points(argv[2], &num_points);
  if (!points) {
    fprintf(stderr, "cannot read %s\n", argv[2]);
    return 1;
  }
  pillarseg_options options;
  pillarseg_default_options(&options);
  if (argc > 4) options.device = argv[4];
  char error[1024];
  pillarseg_segmenter* segmenter = pillarseg_open(argv[1], NULL, &options, error, sizeof error);
  if (!segmenter) {
    fprintf(stderr, "%s\n", error);
    free(points);
    return 1;
  }
  int width = 0, height = 0;
  pillarseg_grid(segmenter, &width, &height);
  const size_t cells = (size_t)width * (size_t)height;
  unsigned char* labels = malloc(cells);
  int status = pillarseg_segment(segmenter, points, num_points, labels, NULL, error, sizeof error);
  if (status != 0) {
    fprintf(stderr, "%s\n", error);
  } else {
    FILE* out = fopen(argv[3], "wb");
    if (!out || fwrite(labels, 1, cells, out) != cells) {
      fprintf(stderr, "cannot write %s\n", argv[3]);
      status = 1;
    }
    if (out) fclose(out);
    size_t histogram[PILLARSEG_NUM_CLASSES + 1] = {0};
    for (size_t i = 0; i < cells; ++i) ++histogram[labels[i]];
    printf("pillarseg %s on %s: %zu points -> %d x %d cells\n", pillarseg_version(),
           pillarseg_device_name(segmenter), num_points, width, height);
    for (int k = 0; k <= PILLARSEG_NUM_CLASSES; ++k)
      if (histogram[k]) printf("  %-13s %zu\n", pillarseg_class_name(k), histogram[k]);
  }
  pillarseg_close(segmenter);
  free(labels);
  free(points);
  return status;
}
