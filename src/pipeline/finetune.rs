//! `doefab finetune`: a fine-tuning job (`crate::decoder::finetune::run_job`) and the chart of
//! its training curve, `training_curve.png` beside the decoder.

use crate::charts::training::write_training_chart;
use crate::decoder::finetune::{run_job, FinetuneJob, FinetuneOutcome, StepStats};
use crate::error::Result;

/// Runs `job` into `job.output` (`on_step` sees every step) and draws its training curve there.
pub fn finetune(job: &FinetuneJob, on_step: &mut dyn FnMut(&StepStats)) -> Result<FinetuneOutcome> {
    let outcome = run_job(job, on_step)?;
    write_training_chart(&outcome.output.join("training_curve.png"), &outcome.history)?;
    Ok(outcome)
}
