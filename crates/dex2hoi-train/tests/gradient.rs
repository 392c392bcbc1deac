//! Finite-difference check of the full objective: the gradient of every term with respect to
//! the prediction (normalised features of both streams) against central differences, in f64.

use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_train::batch::BatchOptions;
use dex2hoi_train::{SurfaceSearch, Term, TrainConfig, Trainer};

/// A `tiny` trainer on a small procedural set with the loss settings `adjust` makes, a batch of
/// three windows, its target (the predicted frames' features, in f64) and a prediction near
/// it, with a random stream for more.
struct Setup {
    config: TrainConfig,
    trainer: Trainer,
    batch: dex2hoi_train::batch::Batch,
    target: Tensor,
    start: Tensor,
    rng: ChaCha8Rng,
}

impl Setup {
    fn new(adjust: impl Fn(&mut TrainConfig)) -> Self {
        let data = dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).unwrap();
        let mut config = TrainConfig::preset("tiny").unwrap();
        adjust(&mut config);
        let trainer =
            Trainer::new(config.clone(), &data, Path::new("procedural"), &Device::Cpu).unwrap();
        let device = Device::Cpu;
        let options = BatchOptions {
            size: 3,
            swap_probability: 0.5,
            mirror_probability: 0.5,
            first_window_share: 0.0,
            put_down_share: 0.0,
        };
        let (tp, tf) = (config.model.prefix_frames, config.model.predicted_frames);
        // The batch of the first seed from 3 on whose windows the contact terms measure
        // something (and the put-down term, when it is on): windows of the person at rest
        // before or after the task have no contact, and a term that measures nothing has no
        // gradient to check.
        for seed in 3..64 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let batch = trainer.training_set().batch(&options, &mut rng, &device).unwrap();
            let target = batch.features.narrow(2, tp, tf).unwrap().to_dtype(DType::F64).unwrap();
            let noise =
                dex2hoi_diffusion::gaussian(target.dims(), &mut rng, DType::F64, &device).unwrap();
            let start = (&target + noise.affine(0.2, 0.0).unwrap()).unwrap();
            let terms = trainer
                .loss_context()
                .objective(&start, &batch, &vec![100; batch.size])
                .unwrap()
                .terms;
            let measured = |term: Term| {
                terms.iter().any(|(t, v)| *t == term && v.to_scalar::<f64>().unwrap() > 0.0)
            };
            let put_down = config.loss.put_down == 0.0 || measured(Term::PutDown);
            if measured(Term::Penetration) && measured(Term::Distance) && put_down {
                return Self { config, trainer, batch, target, start, rng };
            }
        }
        panic!("no batch of seeds 3..64 has a window with contact");
    }
}

#[test]
fn every_term_has_the_gradient_of_its_finite_differences() {
    // The global branch's and the put-down terms are off by default; on here so that every
    // term is checked. The contact terms reach the object rotations too, so that their whole
    // gradient is checked.
    check_finite_differences(
        |config| {
            config.loss.global = 0.01;
            config.loss.put_down = 0.01;
            config.loss.contact_turns_objects = true;
        },
        |_| true,
    );
}

#[test]
fn the_velocity_terms_across_the_seam_have_the_gradient_of_their_finite_differences() {
    check_finite_differences(
        |config| {
            config.loss.global = 0.01;
            config.loss.put_down = 0.01;
            config.loss.velocity_across_the_seam = true;
        },
        |term| matches!(term, Term::FeatureVelocity | Term::JointVelocity),
    );
}

/// Checks the gradient of every term `checked` picks, with the settings `adjust` makes, against
/// central differences at 40 random entries of the prediction and 20 more on its last frame
/// (the only one the put-down term reads).
fn check_finite_differences(adjust: impl Fn(&mut TrainConfig), checked: impl Fn(&Term) -> bool) {
    let Setup { config, trainer, batch, start, mut rng, .. } = Setup::new(adjust);
    let device = Device::Cpu;
    let tf = config.model.predicted_frames;
    let prediction = Var::from_tensor(&start).unwrap();
    let timesteps = vec![100; batch.size];
    let context = trainer.loss_context();
    let objective = |p: &Tensor| context.objective(p, &batch, &timesteps).unwrap();
    let terms = objective(prediction.as_tensor()).terms;
    let of_prediction = Term::ALL.iter().filter(|t| t.reads_prediction()).count();
    assert_eq!(terms.len(), of_prediction);
    let values: Vec<f64> = start.flatten_all().unwrap().to_vec1().unwrap();
    let shape = start.dims().to_vec();
    let width = shape[3];
    let body = 6 * config.model.joints + 3;
    // Entries: rotations, the root and every part of the object features of both slots.
    let mut entries = Vec::new();
    for n in 0..60 {
        let k = if n < 40 { rng.random_range(0..tf) } else { tf - 1 };
        let (i, s) = (rng.random_range(0..shape[0]), rng.random_range(0..2));
        let channel = match rng.random_range(0..3) {
            0 => rng.random_range(0..6 * config.model.joints),
            1 => rng.random_range(6 * config.model.joints..body),
            _ => body + rng.random_range(0..18),
        };
        entries.push(((i * 2 + s) * tf + k) * width + channel);
    }
    for (term, value) in terms.iter().filter(|(term, _)| checked(term)) {
        assert!(
            value.to_scalar::<f64>().unwrap() > 0.0,
            "{} is measured on this batch",
            term.name()
        );
        let gradients = value.backward().unwrap();
        let analytic: Vec<f64> = gradients
            .get(prediction.as_tensor())
            .map(|g| g.flatten_all().unwrap().to_vec1().unwrap())
            .unwrap_or_else(|| vec![0.0; values.len()]);
        let evaluate = |index: usize, delta: f64| -> f64 {
            let mut moved = values.clone();
            moved[index] += delta;
            let p = Tensor::from_vec(moved, shape.as_slice(), &device).unwrap();
            let terms = objective(&p).terms;
            let (_, v) = terms.iter().find(|(t, _)| t == term).unwrap();
            v.to_scalar::<f64>().unwrap()
        };
        let eps = 1e-5;
        let mut checked = 0;
        for &index in &entries {
            let numeric = (evaluate(index, eps) - evaluate(index, -eps)) / (2.0 * eps);
            let tolerance = 1e-4 * numeric.abs().max(analytic[index].abs()) + 1e-6;
            assert!(
                (numeric - analytic[index]).abs() <= tolerance,
                "{}: entry {index}: analytic {} numeric {numeric}",
                term.name(),
                analytic[index]
            );
            checked += usize::from(numeric != 0.0);
        }
        assert!(checked > 0, "{}: no entry with a gradient was checked", term.name());
    }
}

#[test]
fn contact_terms_leave_the_object_channels_alone_when_told_to() {
    // The penetration and `L_dist` gradients on the object channels: rotation (0..6) and the
    // rest (6..18), and on the body's, for each setting of the two options:
    // [rotation, the other object channels, the body] reached.
    for (turns, moves, expected) in [
        (true, true, [true, true, true]),
        (false, true, [false, true, true]),
        (true, false, [false, false, true]),
        (false, false, [false, false, true]),
    ] {
        let reached = channels_reached(
            |config| {
                config.loss.contact_turns_objects = turns;
                config.loss.contact_moves_objects = moves;
            },
            &[Term::Penetration, Term::Distance],
            |body, width| vec![body..body + 6, body + 6..width, 0..body],
        );
        for (term, got) in reached {
            assert_eq!(got, expected, "{} with turns {turns}, moves {moves}", term.name());
        }
    }
}

#[test]
fn the_velocity_terms_see_a_window_that_does_not_continue_its_prefix_only_across_the_seam() {
    // The target with every predicted frame's root 1 cm higher: within the window nothing
    // moves differently from the data, across the seam the whole body jumps 1 cm.
    let velocity = |seam: bool| -> [f64; 2] {
        let Setup { config, trainer, batch, target, .. } = Setup::new(|config| {
            config.loss.velocity_across_the_seam = seam;
        });
        let root = 6 * config.model.joints + 1;
        let std = f64::from(trainer.training_set().stats().std[root]);
        let mut values: Vec<f64> = target.flatten_all().unwrap().to_vec1().unwrap();
        for row in values.chunks_mut(target.dims()[3]) {
            row[root] += 0.01 / std;
        }
        let raised = Tensor::from_vec(values, target.dims(), target.device()).unwrap();
        let terms = trainer
            .loss_context()
            .objective(&raised, &batch, &vec![100; batch.size])
            .unwrap()
            .terms;
        let of = |term: Term| {
            terms.iter().find(|(t, _)| *t == term).unwrap().1.to_scalar::<f64>().unwrap()
        };
        [of(Term::FeatureVelocity), of(Term::JointVelocity)]
    };
    let [features, joints] = velocity(false);
    assert!(features.abs() < 1e-9 && joints.abs() < 1e-9, "{features} {joints}");
    let [features, joints] = velocity(true);
    assert!(features > 0.0, "{features}");
    // 1 cm on every joint at the seam, one step in `T_f`: 1 cm^2 / T_f per joint coordinate
    // that moves (y), a third of the mean over x, y and z.
    let tf = TrainConfig::preset("tiny").unwrap().model.predicted_frames as f64;
    assert!((joints - 1.0 / (3.0 * tf)).abs() < 1e-6, "{joints}");
}

#[test]
fn object_terms_leave_the_root_alone_when_told_to() {
    // The gradients of the terms that read the objects against the predicted body, on the
    // root's displacement and on the joint rotations, for each setting of the option:
    // [the root, the joint rotations] reached.
    for (moves_root, expected) in [(true, [true, true]), (false, [false, true])] {
        let reached = channels_reached(
            |config| config.loss.object_terms_move_root = moves_root,
            &[Term::Translation, Term::Penetration, Term::Distance],
            |body, _| vec![body - 3..body, 0..body - 3],
        );
        for (term, got) in reached {
            assert_eq!(got, expected, "{} with object_terms_move_root {moves_root}", term.name());
        }
    }
}

/// Per term of `terms`, with the settings `adjust` makes, whether its gradient reaches any
/// prediction channel of each range `ranges(body, width)` gives (`body`: the body's width,
/// `6J + 3`; `width`: a stream row's).
fn channels_reached(
    adjust: impl Fn(&mut TrainConfig),
    terms: &[Term],
    ranges: impl Fn(usize, usize) -> Vec<std::ops::Range<usize>>,
) -> Vec<(Term, Vec<bool>)> {
    let Setup { config, trainer, batch, start, .. } = Setup::new(adjust);
    let (body, width) = (6 * config.model.joints + 3, start.dims()[3]);
    let prediction = Var::from_tensor(&start).unwrap();
    let objective =
        trainer.loss_context().objective(prediction.as_tensor(), &batch, &vec![100; batch.size]);
    let values = objective.unwrap().terms;
    terms
        .iter()
        .map(|&term| {
            let (_, value) = values.iter().find(|(t, _)| *t == term).unwrap();
            assert!(value.to_scalar::<f64>().unwrap() > 0.0, "{} is measured", term.name());
            let gradient = value.backward().unwrap();
            let all: Vec<f64> = gradient
                .get(prediction.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let reached = ranges(body, width)
                .into_iter()
                .map(|range| {
                    all.chunks(width).any(|row| row[range.clone()].iter().any(|&g| g != 0.0))
                })
                .collect();
            (term, reached)
        })
        .collect()
}

/// The text term's loss against the cross-entropy written out in f64
/// (`-y ln s - (1 - y) ln(1 - s)`, `s` the sigmoid), and its gradient with respect to the
/// logits against central differences, at logits from -30 to 30 and targets 0, 1 and between.
#[test]
fn the_logistic_loss_is_the_cross_entropy_and_has_its_gradient() {
    let device = Device::Cpu;
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let logits: Vec<f64> = (0..24)
        .map(|k| if k < 4 { [-30.0, -8.0, 8.0, 30.0][k] } else { rng.random_range(-4.0..4.0) })
        .collect();
    let targets: Vec<f64> = (0..24).map(|k| [0.0, 1.0, 0.3][k % 3]).collect();
    let shape = (12, 2);
    let targets_tensor = Tensor::from_vec(targets.clone(), shape, &device).unwrap();
    let loss_at = |values: &[f64]| -> f64 {
        let x = Tensor::from_vec(values.to_vec(), shape, &device).unwrap();
        dex2hoi_train::loss::logistic_loss(&x, &targets_tensor).unwrap().to_scalar().unwrap()
    };
    let written_out: f64 = logits
        .iter()
        .zip(&targets)
        .map(|(&x, &y)| {
            // ln s(x) and ln(1 - s(x)) each in the form that keeps its digits.
            let log_s = if x >= 0.0 { -(-x).exp().ln_1p() } else { x - x.exp().ln_1p() };
            let log_not_s = if x >= 0.0 { -x - (-x).exp().ln_1p() } else { -x.exp().ln_1p() };
            -y * log_s - (1.0 - y) * log_not_s
        })
        .sum::<f64>()
        / logits.len() as f64;
    let value = loss_at(&logits);
    assert!((value - written_out).abs() <= 1e-12 * written_out.abs(), "{value} vs {written_out}");
    let x = Var::from_vec(logits.clone(), shape, &device).unwrap();
    let loss = dex2hoi_train::loss::logistic_loss(x.as_tensor(), &targets_tensor).unwrap();
    let analytic: Vec<f64> = loss
        .backward()
        .unwrap()
        .get(x.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let eps = 1e-6;
    for index in 0..logits.len() {
        let moved = |delta: f64| {
            let mut values = logits.clone();
            values[index] += delta;
            loss_at(&values)
        };
        let numeric = (moved(eps) - moved(-eps)) / (2.0 * eps);
        let tolerance = 1e-6 * numeric.abs().max(analytic[index].abs()) + 1e-9;
        assert!(
            (numeric - analytic[index]).abs() <= tolerance,
            "logit {}: analytic {} numeric {numeric}",
            logits[index],
            analytic[index]
        );
    }
}

/// The text terms' targets sit inside (0, 1), so their best channels are finite: channels of
/// `±ln(0.98 / 0.02) / TEXT_LOGIT_SCALE` (positive for a hand that holds, a side an object
/// ends on) cost less than the same channels halved or doubled, and have no gradient there.
#[test]
fn the_text_terms_are_least_at_finite_channels() {
    use dex2hoi_train::loss::{TEXT_LOGIT_SCALE, TEXT_TARGET_MARGIN};
    let Setup { trainer, batch, .. } = Setup::new(|config| {
        config.loss.text_hands = 1.0;
        config.loss.text_sides = 1.0;
    });
    let best = ((1.0 - TEXT_TARGET_MARGIN) / TEXT_TARGET_MARGIN).ln() / TEXT_LOGIT_SCALE;
    let targets = Tensor::cat(&[&batch.hands, &batch.sides], 1).unwrap();
    let signs = targets.to_dtype(DType::F64).unwrap().affine(2.0, -1.0).unwrap();
    let channels = |size: f64| {
        let rest = Tensor::zeros((batch.size, 4), DType::F64, &Device::Cpu).unwrap();
        Tensor::cat(&[&signs.affine(size, 0.0).unwrap(), &rest], 1).unwrap()
    };
    let terms = |embedding: &Tensor| {
        let terms = trainer.loss_context().text_terms(embedding, &batch).unwrap();
        let names: Vec<Term> = terms.iter().map(|(term, _)| *term).collect();
        assert_eq!(names, [Term::TextHands, Term::TextSides]);
        terms.into_iter().map(|(_, value)| value).collect::<Vec<_>>()
    };
    let costs = |embedding: &Tensor| -> Vec<f64> {
        terms(embedding).iter().map(|v| v.to_scalar::<f64>().unwrap()).collect()
    };
    let at_best = costs(&channels(best));
    for (scale, what) in [(0.5, "halved"), (2.0, "doubled")] {
        for (best, other) in at_best.iter().zip(costs(&channels(scale * best))) {
            assert!(*best < other, "{what} channels cost more: {best} against {other}");
        }
    }
    let embedding = Var::from_tensor(&channels(best)).unwrap();
    for value in terms(embedding.as_tensor()) {
        let gradient = value.backward().unwrap().get(embedding.as_tensor()).unwrap().clone();
        let largest = gradient.abs().unwrap().max_all().unwrap().to_scalar::<f64>().unwrap();
        assert!(largest < 1e-9, "gradient {largest} at the best channels");
    }
}

#[test]
fn the_host_and_tensor_surface_searches_give_the_same_objective() {
    // The tensor search is what a GPU runs; on the CPU both can be asked for. The contact terms,
    // their total and its gradient must not tell them apart.
    let setup = Setup::new(|_| {});
    let prediction = Var::from_tensor(&setup.start).unwrap();
    let timesteps = vec![100; setup.batch.size];
    let run = |search: SurfaceSearch| {
        let context = setup.trainer.loss_context().clone().with_surface_search(search);
        let objective =
            context.objective(prediction.as_tensor(), &setup.batch, &timesteps).unwrap();
        let gradient = objective.total.backward().unwrap().get(&prediction).unwrap().clone();
        let terms: Vec<(Term, f64)> =
            objective.terms.iter().map(|(t, v)| (*t, v.to_scalar::<f64>().unwrap())).collect();
        (terms, gradient)
    };
    let (host_terms, host_gradient) = run(SurfaceSearch::Host);
    let (tensor_terms, tensor_gradient) = run(SurfaceSearch::Tensor);
    assert_eq!(host_terms.len(), tensor_terms.len());
    for ((term, host), (_, tensor)) in host_terms.iter().zip(&tensor_terms) {
        assert!(
            (host - tensor).abs() <= 1e-9 * host.abs().max(1.0),
            "{}: host {host}, tensor {tensor}",
            term.name()
        );
    }
    let difference = (host_gradient - tensor_gradient).unwrap().abs().unwrap();
    let largest = difference.max_all().unwrap().to_scalar::<f64>().unwrap();
    assert!(largest <= 1e-9, "the gradients differ by up to {largest}");
    // Contact was measured: the comparison is not between two zeros.
    assert!(host_terms.iter().any(|(t, v)| *t == Term::Distance && *v > 0.0));
}
