//! The `formation` shells around the pure core: the in-process simulator,
//! run recording and metrics, the zenoh nodes and the command line.
