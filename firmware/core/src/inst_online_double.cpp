// Core template instantiations (online path) for double; see inst_online.inc.
#define MAGVEC_INST_SCALAR double
#include "inst_online.inc"
