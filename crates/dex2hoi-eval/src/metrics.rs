//! Metrics of the paper's tables: distribution metrics on embeddings and physical metrics on
//! motions.
