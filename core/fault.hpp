// Fault injection for the fault tests (DESIGN.md section 9; tests/fault_test.sh): with
// PILLARSEG_FAULT=POINT:N[@RANK] in the environment, the N-th time this process reaches the named
// point it kills itself with SIGKILL - no destructor, no flush, what a crash, an OOM kill or a
// preempted node leaves. @RANK restricts it to that MPI rank (OMPI_COMM_WORLD_RANK, PMI_RANK).
// Points: "step" (inside an optimiser step: after backward, before the update), "write:NAME"
// (inside write_file_atomic of a file named NAME, once bytes of it are on disk, before the
// rename). A POINT ending in '*' matches every point it begins (write:* : any file's write).
// With PILLARSEG_FAULT_STOP=1 as well, the process stops there (SIGSTOP) instead, so that a test
// can hold it at the point while another process runs and kill it when it chooses.
// Without the variable a point costs one branch.
#pragma once

#include <string_view>

namespace pillarseg {

void fault_point(std::string_view point);

}  // namespace pillarseg
