//! `odometer`: the wiring of the example stage (see the library docs): its odometry input, and
//! what it does with each message. The runtime owns the rest (end of stream, summary part, stop).

use odometer::{Odometer, OdometerSettings};
use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::{Input, ProcessContext, Runtime, StageError, Wake};
use shared_types::services::ODOMETRY;
use shared_types::{MsgHeader, OdometryInput};

struct OdometerStage {
    settings: OdometerSettings,
    odometer: Odometer,
    odometry: Input<OdometryInput, MsgHeader>,
}

impl Stage for OdometerStage {
    type Settings = OdometerSettings;

    fn open(_ctx: &ProcessContext, settings: OdometerSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        Ok(Self { settings, odometer: Odometer::default(), odometry: rt.input(ODOMETRY)? })
    }

    fn end_after(&self) -> EndAfter {
        EndAfter::FirstUpstream
    }

    fn step(&mut self, _rt: &mut Runtime, _wake: Wake, _inputs_ended: bool) -> Result<Step, StageError> {
        while let Some(s) = self.odometry.receive()? {
            let u = s.payload();
            if let Err(why) = self.odometer.on_odometry(u.v_mps, u.dt_s, &self.settings) {
                tracing::warn!(seq = s.user_header().seq, "odometry dropped: {why}");
                self.odometry.count_dropped("implausible", 1);
            }
        }
        Ok(Step::Idle)
    }

    type Summary = odometer::OdometerPart;

    fn finish(&mut self, _rt: &mut Runtime, _ending: Ending) -> Result<Self::Summary, StageError> {
        tracing::info!(distance_m = self.odometer.distance_m, messages = self.odometer.messages, "done");
        Ok(self.odometer.summary_part())
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (0, 0) // it publishes nothing
    }
}

fn main() -> std::process::ExitCode {
    pipeline_runtime::stage_main::<OdometerStage>()
}
