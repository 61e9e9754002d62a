//! The report's own checks before anything runs (its errors are
//! [`formation_exit::Error`]).

use formation_exit::Error;

/// Refuses, before anything runs, an `--out` the file system would refuse
/// ([`formation_record::out_path::check_out_path`]).
pub fn check_out(flag: &str, path: &std::path::Path) -> Result<(), Error> {
    use formation_record::out_path::{check_out_path, MAX_OUT_NAME_BYTES};
    check_out_path(flag, path, MAX_OUT_NAME_BYTES).map_err(Error::Input)
}
