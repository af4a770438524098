# The run config of the tiny model the shell tests train (tests/fault_test.sh,
# tests/mpi_train_test.sh): 0.4 m cells on a 40 m x 20 m grid, the 2D occupancy stream, depth 2,
# training on sequence 0 and validation on sequence 08 every epoch. Source this file, then
#   tiny_run_config GROUND_TRUTH EPOCHS BATCH [TRAIN_LINE ...]
# prints it; each TRAIN_LINE ("key: value") is added to the train section after the seed.
tiny_run_config() {
  local ground_truth=$1 epochs=$2 batch=$3 line
  shift 3
  cat <<YAML
grid: {x: [-20.0, 20.0], y: [-10.0, 10.0], z: [-2.5, 1.5], cell: 0.4, voxel_z: 0.2}
model: {max_points_per_pillar: 8, max_pillars: 0, pillars: true, pillar_channels: 8, occupancy: 2d, base_width: 8,
        depth: 2, upsampling: bilinear}
train:
  ground_truth: $ground_truth
  loss: ce
  epochs: $epochs
  batch_size: $batch
  seed: 3
YAML
  for line in "$@"; do echo "  $line"; done
  cat <<'YAML'
  optimizer: {lr: 0.003, weight_decay: 0.01, schedule: onecycle, div_factor: 10, pct_start: 0.4, moms: [0.95, 0.85], grad_clip: 10}
  augmentation: {flip_x: true, flip_y: true, rotate: true, scale: true, translate: false}
  sequences: [0]
eval:
  sequences: [8]
  every_epochs: 1
YAML
}
