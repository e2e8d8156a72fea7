//! Where a fine-tuning run's scenes come from ([`TrainingScenes`]): a folder of images or the
//! procedural generator, cropped and flipped at random.

use std::path::Path;

use crate::decoder::dataset::{training_and_validation, HdrScenes};
use crate::decoder::scenes::{GeneratedScenes, SceneSource};
use crate::error::{Allowed, Error, Result};
use crate::image::Image;

/// A scene generator `f(seed, rows, cols)`.
pub type SceneGenerator = fn(u64, usize, usize) -> Image<f32>;

/// The seeded procedural HDR scenes
/// ([`procedural_scene`](crate::decoder::scenes::procedural_scene)) as a scene source.
pub fn procedural_scenes() -> GeneratedScenes<SceneGenerator> {
    GeneratedScenes { name: "procedural HDR scenes", generate: crate::decoder::scenes::procedural_scene }
}

/// A run's scenes: real HDR images with their validation images, or procedural scenes (which
/// validate on held-out seeds of their own).
pub enum TrainingScenes {
    /// Real HDR images (`finetune --data`).
    Real {
        /// The images trained on.
        training: HdrScenes,
        /// The images validated on: the validation folder's, or those held out of the data.
        validation: HdrScenes,
    },
    /// The seeded procedural HDR scenes ([`procedural_scenes`]), validated on a seed of their
    /// own.
    Procedural(GeneratedScenes<SceneGenerator>),
}

impl TrainingScenes {
    /// The images of `data` as `finetune` takes them ([`training_and_validation`]: validated on
    /// `validation` or on 1 in `holdout_every` of them, panoramas narrower than
    /// `min_panorama_width` left out, colour jitter up to `white_balance`); procedural scenes
    /// without `data`.
    pub fn new(
        data: Option<&Path>,
        validation: Option<&Path>,
        holdout_every: usize,
        min_panorama_width: usize,
        white_balance: f64,
    ) -> Result<TrainingScenes> {
        if !(white_balance >= 1.0 && white_balance.is_finite()) {
            return Err(Error::param_in(
                "white_balance",
                Allowed::at_least(1.0),
                format!("{white_balance} must be finite and >= 1"),
            ));
        }
        Ok(match data {
            Some(dir) => {
                let (mut training, validation) =
                    training_and_validation(dir, validation, holdout_every, min_panorama_width)?;
                training.white_balance = white_balance;
                TrainingScenes::Real { training, validation }
            }
            None => TrainingScenes::Procedural(procedural_scenes()),
        })
    }

    /// Warnings about the images that could not be read (and were skipped).
    pub fn warnings(&self) -> Vec<String> {
        match self {
            TrainingScenes::Real { training, validation } => {
                training.skipped.iter().chain(&validation.skipped).cloned().collect()
            }
            TrainingScenes::Procedural(_) => Vec::new(),
        }
    }

    /// The training source and, for real images, the validation source ([`Trainer::new`]'s).
    ///
    /// [`Trainer::new`]: super::Trainer::new
    pub fn sources(&self) -> (&dyn SceneSource, Option<&dyn SceneSource>) {
        match self {
            TrainingScenes::Real { training, validation } => (training, Some(validation)),
            TrainingScenes::Procedural(p) => (p, None),
        }
    }
}
