//! Metrics of the paper's tables: distribution metrics on embeddings and physical metrics on
//! motions (paper Sec. 4.2; docs/CONVENTIONS.md, "Evaluation protocols").
//!
//! **Embedding metrics** follow the MDM / T2M evaluation protocol: [`fid`], [`diversity`],
//! [`multimodality`], [`r_precision`] (from [`retrieval_ranks`], each pair's rank, so that a
//! subset's share is [`top_k_shares`] of its ranks) and [`matching_distance`] (MMdist), all
//! computed in `f64` on rows of evaluator embeddings, and [`mean_interval`] for the mean and 95% interval over
//! replications. Random draws (pairs, shuffles) come from a seeded ChaCha8 generator, so a seed
//! reproduces a number exactly.
//!
//! **Motion metrics** work on one sample at a time, described by a [`MotionSample`] (joint
//! positions, object poses, object meshes, optional mixture weights): [`penetration`],
//! [`hand_contact`] and [`contact_scores`] (CHOIS), [`foot_sliding`] (MANN's weighted foot
//! displacement), [`mixture_agreement`] (does the mixture of Eq. 4 pick the hand that holds the
//! object?), [`instruction_following`] (does a clip move the objects its ground truth moves,
//! with the same hands, to the same place?), [`object_start_jumps`], [`object_start_turns`],
//! [`untouched_object_motion`] (speeds and turning rates; [`turn_degrees`] in `f64`) and
//! [`object_sinking`] (do objects behave like objects?),
//! [`long_generation`] (a motion of many seconds against its whole ground truth: the task done
//! as asked and once, objects at rest on their support),
//! [`fingertip_distances`] (how precisely the fingertips sit on a held object) and [`runtime`]. Each per-sample result carries its counts so that a test set can be
//! pooled ([`Penetration::pooled`], [`ContactCounts::merge`]).
//!
//! Conventions: metres, Y up, floor at `y = 0`; object meshes in their own (bounding-box-centred)
//! frame and object rotations stored row-major as in
//! [`ProcessedSequence`](dex2hoi_data::features::ProcessedSequence); object slots are the two of
//! [`MAX_OBJECTS`](dex2hoi_data::MAX_OBJECTS).
//!
//! Layout (private submodules, everything public re-exported here): `distribution` (FID,
//! Diversity, MultiModality) and `matching` (R-precision, MMdist) on embeddings, with the
//! symmetric eigen-solver FID needs in `linalg`; `sample` (the [`MotionSample`] the physical
//! metrics read), `penetration`, `contact`, `foot_sliding`, `mixture`, `instruction` and `grasp`
//! on motions;
//! `statistics` for the intervals over replications, runtime and quantiles.

mod contact;
mod distribution;
mod embedding;
mod foot_sliding;
mod grasp;
mod instruction;
mod linalg;
mod long_generation;
mod matching;
mod mixture;
mod penetration;
mod sample;
mod statistics;

pub use contact::{
    CONTACT_RADIUS_M, ContactCounts, ContactScores, contact_counts, contact_flags, contact_scores,
    hand_contact, hand_object_distances,
};
pub use distribution::{
    DIVERSITY_PAIRS, EmbeddingStatistics, MultimodalityProtocol, diversity, fid,
    fid_from_statistics, multimodality,
};
pub use foot_sliding::{ANKLE_HEIGHT_M, TOE_HEIGHT_M, foot_sliding};
pub use grasp::fingertip_distances;
pub use instruction::{
    Holder, InstructionCounts, MOVED_RISE_M, MOVED_TRAVEL_M, SIDE_MARGIN_M, SINK_TOLERANCE_M, Side,
    Sinking, UNTOUCHED_DISTANCE_M, instruction_following, median, object_sinking,
    object_start_jumps, object_start_turns, turn_degrees, untouched_object_motion,
    untouched_object_speeds, untouched_object_turn_rates,
};
pub use linalg::{SymmetricEigen, symmetric_eigen};
pub use long_generation::{
    HandsUsed, LIFT_M, LongCounts, MIN_HOLD_S, MIN_LIFT_S, ObjectCourse, PUT_DOWN_GAP_S,
    SeamCourse, judge_courses, lift_count, long_generation, long_medians, object_courses,
    seam_course,
};
pub use matching::{
    R_PRECISION_BATCH, Retrieval, matching_distance, r_precision, r_precision_of_ranks,
    r_precision_with, retrieval_ranks, top_k_shares,
};
pub use mixture::{mixture_agreement, mixture_agreement_counts, mixture_weights_from_features};
pub use penetration::{PENETRATION_TOLERANCE_M, Penetration, penetration};
pub use sample::MotionSample;
pub(crate) use sample::rotation_from_rows;
pub use statistics::{CONFIDENCE_Z, mean_interval, quantile, runtime};
