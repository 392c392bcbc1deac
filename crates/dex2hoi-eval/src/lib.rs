//! Evaluation of dex2hoi (paper Sec. 4.2-4.3, docs/CONVENTIONS.md, "Evaluation protocols"): learned
//! evaluators (a contrastive text-motion model and an action classifier), the metrics of the
//! paper's tables (FID, Diversity, MultiModality, R-precision, MMdist, penetration, contact, foot
//! sliding, mixture agreement, runtime) and the evaluation report.

pub mod error;
pub mod evaluate;
pub mod evaluator;
pub mod metrics;

pub use error::{EvalError, Result};
