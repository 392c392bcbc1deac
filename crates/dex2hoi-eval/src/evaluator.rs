//! Learned evaluators: a contrastive text-motion model and an action classifier.
