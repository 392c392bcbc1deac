//! AdamW and the EMA have two implementations, the host loop (the CPU's) and tensor operations
//! (every other device's). The tensor path runs on the CPU too, so here the two are compared
//! over several updates: moments, weights and averages within float rounding, with clipping
//! active, a parameter that gets no gradient, and results that keep no autograd graph.

use candle_core::{DType, Device, Tensor, Var};

use dex2hoi_optim::{AdamW, Ema, OptimizerConfig, Parameter};

fn parameters() -> Vec<Parameter> {
    let values = |n: usize, shift: f32| -> Vec<f32> {
        (0..n).map(|k| (k as f32 * 0.37 + shift).sin() * 0.5).collect()
    };
    let var = |shape: &[usize], shift: f32| {
        let n = shape.iter().product();
        Var::from_tensor(&Tensor::from_vec(values(n, shift), shape, &Device::Cpu).unwrap()).unwrap()
    };
    vec![
        Parameter { name: "a.weight".into(), var: var(&[7, 5], 0.1) },
        Parameter { name: "a.bias".into(), var: var(&[5], 0.7) },
        Parameter { name: "unused.weight".into(), var: var(&[3, 2], 1.3) },
    ]
}

fn copy(parameters: &[Parameter]) -> Vec<Parameter> {
    parameters
        .iter()
        .map(|p| Parameter {
            name: p.name.clone(),
            var: Var::from_tensor(&p.var.as_tensor().copy().unwrap()).unwrap(),
        })
        .collect()
}

/// A loss of the first two parameters (the third gets no gradient), different at each step.
fn loss(parameters: &[Parameter], step: usize) -> Tensor {
    let input = Tensor::from_vec(
        (0..21).map(|k| ((k + step) as f32 * 0.9).cos()).collect::<Vec<f32>>(),
        (3, 7),
        &Device::Cpu,
    )
    .unwrap();
    let out = input.matmul(parameters[0].var.as_tensor()).unwrap();
    let out = out.broadcast_add(parameters[1].var.as_tensor()).unwrap();
    (out.sqr().unwrap().sum_all().unwrap() * 40.0).unwrap()
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_dtype(DType::F32).unwrap().to_vec1().unwrap()
}

fn largest_difference(a: &Tensor, b: &Tensor) -> f32 {
    values(a).iter().zip(values(b)).fold(0f32, |m, (x, y)| m.max((x - y).abs()))
}

#[test]
fn the_tensor_path_updates_as_the_host_loop_does() {
    let config = OptimizerConfig { gradient_clip: Some(1.0), ..OptimizerConfig::default() };
    let host = parameters();
    let tensor = copy(&host);
    let mut host_adam = AdamW::new(config.clone(), &host).unwrap();
    let mut tensor_adam = AdamW::new(config, &tensor).unwrap();
    let mut host_ema = Ema::new(&host).unwrap();
    let mut tensor_ema = Ema::new(&tensor).unwrap();
    for step in 0..6 {
        let host_grads = loss(&host, step).backward().unwrap();
        let tensor_grads = loss(&tensor, step).backward().unwrap();
        let a = host_adam.update_on(&host, &host_grads, 1e-2, true).unwrap();
        let b = tensor_adam.update_on(&tensor, &tensor_grads, 1e-2, false).unwrap();
        assert!(a.gradient_norm > 1.0, "clipping is active: {}", a.gradient_norm);
        assert!((a.gradient_norm - b.gradient_norm).abs() / a.gradient_norm < 1e-5);
        host_ema.update_on(&host, 0.9, step, true).unwrap();
        tensor_ema.update_on(&tensor, 0.9, step, false).unwrap();
    }
    for (k, (h, t)) in host.iter().zip(&tensor).enumerate() {
        assert!(largest_difference(h.var.as_tensor(), t.var.as_tensor()) < 1e-6, "{}", h.name);
        let ((h1, h2), (t1, t2)) = (host_adam.moments(k), tensor_adam.moments(k));
        assert!(largest_difference(h1, t1) < 1e-6 && largest_difference(h2, t2) < 1e-6);
        assert!(largest_difference(host_ema.value(k), tensor_ema.value(k)) < 1e-6);
        // Nothing the state holds keeps a graph alive from one step to the next.
        assert!(!t1.track_op() && !t2.track_op() && !tensor_ema.value(k).track_op());
    }
    // The parameter without a gradient still decayed, by both paths alike.
    let before = values(parameters()[2].var.as_tensor());
    assert!(values(host[2].var.as_tensor()).iter().zip(&before).any(|(a, b)| a != b));
}

#[test]
fn the_update_with_its_average_is_the_update_then_the_average() {
    // The fused kernel is asked for (the default) but needs a GPU: the CPU updates the
    // parameters and then their average with its host loops, and a non-finite gradient norm
    // leaves the average alone.
    let config = OptimizerConfig::default();
    assert!(config.fused);
    let together = parameters();
    let apart = copy(&together);
    let mut adams =
        [AdamW::new(config.clone(), &together).unwrap(), AdamW::new(config, &apart).unwrap()];
    let mut averages = [Ema::new(&together).unwrap(), Ema::new(&apart).unwrap()];
    for step in 0..3 {
        let grads = loss(&together, step).backward().unwrap();
        let [a, b] = &mut adams;
        let [ea, eb] = &mut averages;
        let ours = a.update_with_average(ea, &together, &grads, 1e-2, (0.9, step)).unwrap();
        let grads = loss(&apart, step).backward().unwrap();
        let theirs = b.update(&apart, &grads, 1e-2).unwrap();
        eb.update(&apart, 0.9, step).unwrap();
        assert_eq!(ours, theirs);
    }
    for (k, (t, a)) in together.iter().zip(&apart).enumerate() {
        assert_eq!(values(t.var.as_tensor()), values(a.var.as_tensor()), "{}", t.name);
        assert_eq!(values(averages[0].value(k)), values(averages[1].value(k)), "{}", t.name);
    }
    let average_before = values(averages[0].value(0));
    let grads = (loss(&together, 3) * f64::NAN).unwrap().backward().unwrap();
    let [a, _] = &mut adams;
    let [ea, _] = &mut averages;
    let report = a.update_with_average(ea, &together, &grads, 1e-2, (0.9, 3)).unwrap();
    assert!(!report.gradient_norm.is_finite());
    assert_eq!(values(averages[0].value(0)), average_before);
}
