// The CPU backend's pillar feature net (the contract of Backend::pfn_forward / pfn_backward, the
// semantics of host/pfn.hpp): points (P, N, 10), weight (C, 10) -> out (P, C) = max over the N
// slots of ReLU(BatchNorm(points . weight^T)), and its training backward, computed per block of
// pillars so that the linear output z (P N, C), 200 MB on a real scan, never exists whole: each
// pass recomputes its block's z (10 multiply-adds a value) in a buffer of its thread.
//   training forward: [sums] per block, the sum of z per channel in double, added over the blocks
//     in block order (and over the replicas) -> the mean; [squares] the same for (z - mean)^2 ->
//     the biased variance (two passes, as host/batchnorm.cpp); [apply] BatchNorm + ReLU and the
//     max over the slots, with the arg-max slot (torch.max's: the first maximum, NaN wins; -1
//     where the max is not > 0);
//   backward: [sums] of the routed gradient g = dout(p, c) at its slot and of g xhat, over the
//     P C routed rows only (every other row's g is 0), per block then in block order -> dgamma,
//     dbeta and, summed over the replicas, BatchNorm's input-gradient coefficients; [weight]
//     per block, dz = BatchNorm's input gradient of g (every row has one) and its block's part of
//     dweight = dz^T points, the parts added in block order in double.
// Every sum is per block of a fixed size and then in block order: the results do not depend on
// the thread count. The points' own gradient is not computed (they are the network's input).
#pragma once

#include "engine/backend/backend.hpp"

namespace pillarseg::cpu {

// Evaluation: the running statistics of bn.
void pfn_forward_eval(const Ref& points, const Ref& weight, const BatchNormRefs& bn, Ref& out);
// Training: batch statistics (of all replicas when bn.replicas is set) into bn.save_mean and
// bn.save_invstd, the running statistics updated in place, argmax (P, C) for the backward.
void pfn_forward_train(const Ref& points, const Ref& weight, BatchNormRefs& bn, IRef& argmax,
                       Ref& out);
// dout (P, C) -> dweight (C, 10), dgamma, dbeta (C), from the training forward's bn.save_* and
// argmax.
void pfn_backward(const Ref& points, const Ref& weight, const BatchNormRefs& bn, const IRef& argmax,
                  const Ref& dout, Ref& dweight, Ref& dgamma, Ref& dbeta);

}  // namespace pillarseg::cpu
