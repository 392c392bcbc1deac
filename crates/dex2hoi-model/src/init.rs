//! Seeded parameter initialisation: candle's CPU generator cannot be seeded, so every parameter
//! is drawn from its own stream, seeded by the model seed and the parameter's name (creation
//! order does not matter), with the distribution candle would use for it.

use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::init::{Init, NormalOrUniform};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// What the variables created on a thread may still take ([`with_parameter_budget`]).
struct Budget {
    left: usize,
    total: usize,
    refused: Option<String>,
}

thread_local! {
    static BUDGET: std::cell::RefCell<Option<Budget>> = const { std::cell::RefCell::new(None) };
}

/// The [`with_parameter_budget`] for loading a file whose tensors hold `file_values` values:
/// twice those and a million more. A model that fits its file needs at most as many; the slack
/// lets one that misses a few parameters still be built, so that loading names the missing
/// parameter rather than the budget, while what a file can make the loader allocate stays
/// proportional to its size.
pub fn parameter_budget(file_values: usize) -> usize {
    file_values.saturating_mul(2).saturating_add(1 << 20)
}

/// Runs `build` with the new variables of every [`SeededVarMap`] it creates on this thread
/// limited to `elements` values in all, and returns what `build` returned with the first
/// parameter refused, if any (a refused parameter is an error inside `build`, raised before
/// anything is allocated for it). Loading a file builds its networks from sizes in the file's
/// metadata before the weights are matched to them: with the file's own count of weight
/// values as the limit, hostile sizes cannot allocate more than the file holds.
pub fn with_parameter_budget<T>(elements: usize, build: impl FnOnce() -> T) -> (T, Option<String>) {
    /// Restores the enclosing budget, also when `build` panics.
    struct Restore(Option<Budget>);
    impl Drop for Restore {
        fn drop(&mut self) {
            BUDGET.with(|b| *b.borrow_mut() = self.0.take());
        }
    }
    let outer =
        BUDGET.with(|b| b.replace(Some(Budget { left: elements, total: elements, refused: None })));
    let restore = Restore(outer);
    let built = build();
    let refused = BUDGET.with(|b| b.borrow_mut().as_mut().and_then(|b| b.refused.take()));
    drop(restore);
    (built, refused)
}

/// Takes a new parameter's values from the thread's budget, if one is set; `Err` says why not.
fn take_from_budget(shape: &Shape, name: &str) -> Result<(), String> {
    BUDGET.with(|budget| {
        let mut budget = budget.borrow_mut();
        let Some(budget) = budget.as_mut() else { return Ok(()) };
        let count = shape.dims().iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        match count {
            Some(count) if count <= budget.left => {
                budget.left -= count;
                Ok(())
            }
            _ => {
                let why = format!(
                    "parameter {name} of shape {:?}, past the {} values left of {}",
                    shape.dims(),
                    budget.left,
                    budget.total
                );
                budget.refused.get_or_insert_with(|| why.clone());
                Err(why)
            }
        }
    })
}

/// A [`VarMap`] whose new variables are initialised from a seed.
#[derive(Clone)]
pub struct SeededVarMap {
    map: VarMap,
    seed: u64,
}

impl std::fmt::Debug for SeededVarMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let count = self.map.data().lock().map(|d| d.len()).unwrap_or(0);
        f.debug_struct("SeededVarMap")
            .field("seed", &self.seed)
            .field("parameters", &count)
            .finish()
    }
}

impl SeededVarMap {
    /// An empty map.
    pub fn new(seed: u64) -> Self {
        Self { map: VarMap::new(), seed }
    }

    /// The underlying map (every trained variable).
    pub fn var_map(&self) -> &VarMap {
        &self.map
    }

    /// A builder whose variables land in this map.
    pub fn builder(&self, dtype: DType, device: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), dtype, device.clone())
    }

    /// Redraws, from `seed`, every parameter that is all zeros (the AdaLN modulations and the
    /// output heads start at zero): weights `[input, output]` uniformly in `+-1/sqrt(input)`,
    /// vectors in `+-0.1`. An untrained model outputs exact zeros, which would compare equal
    /// to anything; benchmarks and equivalence tests use this to make every layer do work.
    pub fn randomise_zero_parameters(&self, seed: u64) -> candle_core::Result<()> {
        let data = self.map.data().lock().expect("the variable map's lock");
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        for name in names {
            let var = &data[name];
            let values: Vec<f32> =
                var.as_tensor().flatten_all()?.to_dtype(DType::F32)?.to_vec1()?;
            if values.iter().any(|&v| v != 0.0) {
                continue;
            }
            let bound = match var.dims() {
                [input, _] => 1.0 / (*input as f64).sqrt(),
                _ => 0.1,
            };
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ fnv1a(name));
            let drawn: Vec<f64> =
                (0..values.len()).map(|_| rng.random_range(-bound..bound)).collect();
            let drawn =
                Tensor::from_vec(drawn, var.shape(), var.device())?.to_dtype(var.dtype())?;
            var.set(&drawn)?;
        }
        Ok(())
    }

    fn initial(&self, shape: &Shape, name: &str, init: Init) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ fnv1a(name));
        let count = shape.elem_count();
        let uniform = |rng: &mut ChaCha8Rng, lo: f64, up: f64| {
            (0..count).map(|_| rng.random_range(lo..up)).collect()
        };
        let normal = |rng: &mut ChaCha8Rng, mean: f64, std: f64| {
            (0..count).map(|_| mean + std * rng.sample::<f64, _>(StandardNormal)).collect()
        };
        match init {
            Init::Const(value) => vec![value; count],
            Init::Uniform { lo, up } => uniform(&mut rng, lo, up),
            Init::Randn { mean, stdev } => normal(&mut rng, mean, stdev),
            Init::Kaiming { dist, fan, non_linearity } => {
                let std = non_linearity.gain() / (fan.for_shape(shape) as f64).sqrt();
                match dist {
                    NormalOrUniform::Uniform => {
                        uniform(&mut rng, -(3f64.sqrt()) * std, 3f64.sqrt() * std)
                    }
                    NormalOrUniform::Normal => normal(&mut rng, 0.0, std),
                }
            }
        }
    }
}

impl SimpleBackend for SeededVarMap {
    fn get(
        &self,
        shape: Shape,
        name: &str,
        init: Init,
        dtype: DType,
        device: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut data = self.map.data().lock().expect("the var map lock is not poisoned");
        if let Some(var) = data.get(name) {
            if var.shape() != &shape {
                candle_core::bail!(
                    "parameter {name}: shape {:?} already registered, asked for {shape:?}",
                    var.shape()
                );
            }
            return Ok(var.as_tensor().clone());
        }
        if let Err(why) = take_from_budget(&shape, name) {
            candle_core::bail!("{why}");
        }
        let values = self.initial(&shape, name, init);
        let tensor = Tensor::from_vec(values, shape, device)?.to_dtype(dtype)?;
        let var = Var::from_tensor(&tensor)?;
        data.insert(name.to_string(), var.clone());
        Ok(var.as_tensor().clone())
    }

    fn get_unchecked(
        &self,
        name: &str,
        _dtype: DType,
        _device: &Device,
    ) -> candle_core::Result<Tensor> {
        let data = self.map.data().lock().expect("the var map lock is not poisoned");
        match data.get(name) {
            Some(var) => Ok(var.as_tensor().clone()),
            None => candle_core::bail!("parameter {name} is not in the model"),
        }
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.map.data().lock().expect("the var map lock is not poisoned").contains_key(name)
    }
}

/// FNV-1a of a name: a hash that never changes between builds (std's hasher may).
fn fnv1a(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |hash, byte| {
        (hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3)
    })
}
