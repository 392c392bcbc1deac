//! What the tests and benchmarks of several dex2hoi crates share, as a crate of its own so that
//! none of them compiles another's files: a small SMPL-X model file written on any skinned body
//! ([`smplx_fixture`]) and the peak resident memory of the process ([`memory`]). It depends on
//! no dex2hoi crate; crates take it as a dev-dependency only.

pub mod memory;
pub mod smplx_fixture;
