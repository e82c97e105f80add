//! Dropout seeds drawn ahead are the ones a sequential run draws, so the fusion branches may run
//! side by side in training without changing a mask (`Reconstructor::fuse_branches`). In its
//! own test binary because Burn's device RNG is process-wide: tests running in parallel in one
//! process would draw from it between `seed` and the draws.

use burn::module::Module;
use burn::tensor::{Device, Distribution, Tensor};
use lifegom_model::fusion::{FusionConfig, FusionMasks, FusionRun};
use lifegom_model::norm_folds::NormFolds;

fn read(t: Tensor<2>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

fn sequential_and_drawn_ahead_agree(device: &Device) {
    let ad = device.clone().autodiff();
    let fusion = FusionConfig::new(12)
        .with_n_heads(2)
        .with_dropout(0.3)
        .init(&ad);
    let normal =
        |shape: [usize; 3]| Tensor::<3>::random(shape, Distribution::Normal(0.0, 1.0), &ad);
    let (src, ren) = (normal([40, 3, 12]), normal([40, 3, 12]));
    let embed = Tensor::<2>::random([40, 12], Distribution::Normal(0.0, 1.0), &ad);

    // Burn initialises parameters lazily, from the same RNG, on their first use: one call
    // first, so that only dropout draws between `seed` and the comparison.
    let _ = fusion.forward(
        &NormFolds::new(),
        src.clone(),
        embed.clone(),
        FusionRun::default(),
    );

    // Sequential: each call draws its four masks from the device RNG as it goes.
    ad.seed(5);
    let seq_src = read(fusion.forward(
        &NormFolds::new(),
        src.clone(),
        embed.clone(),
        FusionRun::default(),
    ));
    let seq_ren = read(
        fusion
            .forward(
                &NormFolds::new(),
                ren.clone(),
                embed.clone(),
                FusionRun::default(),
            )
            .detach(),
    );

    // Ahead: both calls' seeds first, source then rendered; the rendered call on an inference
    // copy of the weights, as on the second thread.
    ad.seed(5);
    let src_masks = fusion.draw_mask_seeds(&ad).expect("a host device");
    let ren_masks = fusion.draw_mask_seeds(&ad).expect("a host device");
    let given = |seeds| FusionRun {
        masks: FusionMasks::Given(seeds),
        repeats: None,
    };
    let ahead_src = read(fusion.forward(&NormFolds::new(), src, embed.clone(), given(src_masks)));
    let ahead_ren = read(fusion.valid().forward(
        &NormFolds::new(),
        ren.inner(),
        embed.inner(),
        given(ren_masks),
    ));
    assert_eq!(seq_src, ahead_src, "source branch");
    assert_eq!(seq_ren, ahead_ren, "rendered branch");
}

#[test]
#[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
fn drawn_ahead_masks_equal_the_sequential_draws() {
    for device in [Device::ndarray(), Device::flex()] {
        sequential_and_drawn_ahead_agree(&device);
    }
}
