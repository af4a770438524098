// The architecture of a weights-only checkpoint (for example one exported from PyTorch with the
// authors' module names, DESIGN.md section 2), read from its tensor shapes:
//   vfe.pfn_layers.0.linear.weight (C, 10)                       -> the pillar stream and C
//   occupancy.conv.weight (Q, I, 3, 3)                           -> the occupancy stream and Q;
//                                                                   I = 1: 2D observability, the
//                                                                   grid's Z layers: 3D occupancy
//   segmentation_head.down1.maxpool_conv.1.double_conv.0.weight  -> the U-Net's input channels
//     (2b, C + Q + G, 3, 3)                                         (G = 6: the grid-map input)
//   segmentation_head.downK...                                   -> depth (the last K present)
//   segmentation_head.up1.up.weight                              -> transposed (else bilinear)
//   segmentation_head.outc.conv.weight (12, b, 1, 1)             -> b
// The grid is the caller's (the paper's by default); what no tensor holds keeps its default (N =
// 20 points per pillar, P = 0). The model built from the result must then hold exactly the file's
// tensors, which load_weights checks (naming any that does not fit).
#pragma once

#include "core/grid.hpp"
#include "engine/model/config.hpp"
#include "weights_io/safetensors.hpp"

namespace pillarseg {

// Throws pillarseg::Error naming the file, the tensor that fits no architecture and why.
ModelConfig model_config_from_tensors(const weights::SafeTensors& file, const GridSpec& grid = {});

}  // namespace pillarseg
