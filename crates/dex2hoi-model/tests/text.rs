//! The built-in text encoder and the cache.

use candle_core::{DType, Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use dex2hoi_model::SeededVarMap;
use dex2hoi_model::text::{
    BuiltinTextConfig, BuiltinTextEncoder, FrozenCache, TextEncoder, UNKNOWN, Vocabulary, words,
};

fn corpus() -> Vec<&'static str> {
    vec![
        "The person picks up the mug with the left hand.",
        "Someone pours from the bottle into the bowl.",
    ]
}

#[test]
fn vocabulary_and_unknown_words() {
    let vocabulary = Vocabulary::from_texts(corpus());
    assert_eq!(words("Left-hand, MUG!"), vec!["left", "hand", "mug"]);
    let ids = vocabulary.tokenize("the person juggles the mug");
    assert_eq!(ids.len(), 5);
    assert_eq!(ids[2], UNKNOWN, "an unknown word becomes [UNK]");
    assert!(ids.iter().enumerate().all(|(k, &id)| k == 2 || id > UNKNOWN));
    assert_eq!(Vocabulary::from_words(vocabulary.words().to_vec()), vocabulary);
}

#[test]
fn builtin_encoder_embeds_and_refuses_empty_prompts() {
    let vars = SeededVarMap::new(3);
    let config = BuiltinTextConfig { width: 16, layers: 2, heads: 2, max_tokens: 12, output: 8 };
    let encoder = BuiltinTextEncoder::new(
        Vocabulary::from_texts(corpus()),
        config,
        vars.builder(DType::F32, &Device::Cpu),
    )
    .unwrap();
    let out = encoder.encode(&["the person picks up the mug", "pours"]).unwrap();
    assert_eq!(out.dims(), &[2, 8]);
    let rows = out.to_vec2::<f32>().unwrap();
    assert_ne!(rows[0], rows[1]);
    // Padding does not change a text's embedding.
    let alone = encoder.encode(&["pours"]).unwrap().to_vec2::<f32>().unwrap();
    for (a, b) in alone[0].iter().zip(&rows[1]) {
        assert!((a - b).abs() < 1e-5);
    }
    let error = encoder.encode(&["", "mug"]).unwrap_err().to_string();
    assert!(error.contains("empty"), "{error}");
    assert!(encoder.encode(&["?!"]).is_err(), "no words at all");
}

#[test]
fn builtin_encoder_gradients_match_finite_differences() {
    let vars = SeededVarMap::new(4);
    let config = BuiltinTextConfig { width: 8, layers: 1, heads: 2, max_tokens: 8, output: 4 };
    let encoder = BuiltinTextEncoder::new(
        Vocabulary::from_texts(corpus()),
        config,
        vars.builder(DType::F64, &Device::Cpu),
    )
    .unwrap();
    let texts = ["the mug", "someone pours from the bottle"];
    let weights =
        Tensor::new(&[[0.3f64, -0.7, 0.2, 0.9], [-0.4, 0.5, 0.8, -0.1]], &Device::Cpu).unwrap();
    let loss = || (encoder.encode(&texts).unwrap() * &weights).unwrap().sum_all().unwrap();
    let grads = loss().backward().unwrap();
    let data = vars.var_map().data().lock().unwrap();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for name in names {
        let var = &data[name];
        let grad: Vec<f64> =
            grads.get(var.as_tensor()).unwrap().flatten_all().unwrap().to_vec1().unwrap();
        let base: Vec<f64> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
        // Token rows of words not in the texts have no gradient: pick entries that do.
        let candidates: Vec<usize> = (0..base.len()).filter(|&i| grad[i] != 0.0).collect();
        assert!(!candidates.is_empty(), "{name}: no gradient at all");
        for _ in 0..3 {
            let i = candidates[rng.random_range(0..candidates.len())];
            let at = |delta: f64| {
                let mut v = base.clone();
                v[i] += delta;
                var.set(&Tensor::from_vec(v, var.shape(), &Device::Cpu).unwrap()).unwrap();
                loss().to_scalar::<f64>().unwrap()
            };
            let numeric = (at(1e-6) - at(-1e-6)) / 2e-6;
            var.set(&Tensor::from_vec(base.clone(), var.shape(), &Device::Cpu).unwrap()).unwrap();
            assert!(
                (numeric - grad[i]).abs() <= 1e-6 + 1e-5 * numeric.abs(),
                "{name}[{i}]: {} vs {numeric}",
                grad[i]
            );
        }
    }
}

struct Counting(std::cell::Cell<usize>);

impl TextEncoder for Counting {
    fn embedding_size(&self) -> usize {
        2
    }
    fn encode(&self, texts: &[&str]) -> dex2hoi_model::Result<Tensor> {
        self.0.set(self.0.get() + texts.len());
        let rows: Vec<f32> = texts.iter().flat_map(|t| [t.len() as f32, 1.0]).collect();
        Ok(Tensor::from_vec(rows, (texts.len(), 2), &Device::Cpu)?)
    }
}

#[test]
fn frozen_cache_encodes_each_text_once() {
    let cache = FrozenCache::new(Counting(std::cell::Cell::new(0)));
    let a = cache.encode(&["mug", "bowl", "mug"]).unwrap().to_vec2::<f32>().unwrap();
    assert_eq!(a, vec![vec![3.0, 1.0], vec![4.0, 1.0], vec![3.0, 1.0]]);
    cache.encode(&["bowl", "plate"]).unwrap();
    assert_eq!(cache.cached(), 3);
}
