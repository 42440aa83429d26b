// The motion kernels as one translation unit: the ARAP regulariser, the velocity and acceleration terms, the DQB
// skinning and the relative node motions it blends (each file registers its own ops). Compiled apart, each file
// spent about 4.5 s of a cold build parsing the same ATen headers; here they are parsed once
// (kernel_build.INCLUDED_SOURCES, docs/rendering.md). The files share one anonymous namespace in this unit, so
// their helpers must not share a name (a clash is a compile error, an overload would be silent).
#include "arap_cpu.cpp"
#include "skinning_cpu.cpp"
#include "quat_cpu.h"
#include "relative_cpu.cpp"
#include "smooth_cpu.cpp"
