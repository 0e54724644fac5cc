//! Where a restarted ingest resumes: the stage records, before it publishes each item, how many
//! items it has taken from its source (plus its counters) as a line of the runtime's journal
//! ([`pipeline_runtime::Runtime::state`]). A
//! restarted instance (the supervisor sets `SLAM_PIPELINE_RESTARTS` > 0) reads it, takes that many
//! items from the (deterministic) source without publishing them, and goes on with the next one:
//! downstream sees the stream continue with newer stamps instead of the mission replayed from the
//! start. Recording before publishing makes the delivery at most once: a kill between the record
//! and the send loses that one item, it never duplicates one.
//!
//! One line per item (one `write` each, flushed before the send); the runtime drops a line cut
//! short by a kill.

/// What a killed instance had done.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Progress {
    /// Items taken from the source (published, skipped as empty, or lost to the kill).
    pub items: u64,
    /// Messages published per service: odometry, stereo, buoy ranges, depth, cloud, heading,
    /// laser, planar odometry.
    pub counts: [u64; 8],
    /// Empty clouds skipped.
    pub empty_clouds: u64,
    /// Stamp of the first and of the last item taken, ns.
    pub first_last_stamp: Option<(u64, u64)>,
}

impl Progress {
    /// The record's text (without padding).
    pub fn encode(&self) -> String {
        let (a, b) = self.first_last_stamp.unwrap_or((0, 0));
        let c = self.counts;
        format!(
            "v1 items={} counts={},{},{},{},{},{},{},{} empty={} first={} last={} stamped={}",
            self.items,
            c[0],
            c[1],
            c[2],
            c[3],
            c[4],
            c[5],
            c[6],
            c[7],
            self.empty_clouds,
            a,
            b,
            u8::from(self.first_last_stamp.is_some())
        )
    }

    /// Parses a record written by [`Progress::encode`] (trailing padding allowed).
    pub fn decode(text: &str) -> Option<Self> {
        let mut fields = text.split_whitespace();
        if fields.next()? != "v1" {
            return None;
        }
        let mut value = |key: &str| fields.next()?.strip_prefix(key)?.strip_prefix('=').map(str::to_string);
        let items = value("items")?.parse().ok()?;
        let counts_text = value("counts")?;
        let empty_clouds = value("empty")?.parse().ok()?;
        let first: u64 = value("first")?.parse().ok()?;
        let last: u64 = value("last")?.parse().ok()?;
        let stamped = value("stamped")? == "1";
        let mut counts: Vec<u64> = counts_text.split(',').map(str::parse).collect::<Result<_, _>>().ok()?;
        // Records written before the laser and planar odometry services had six counts.
        if counts.len() == 6 {
            counts.extend([0, 0]);
        }
        Some(Self {
            items,
            counts: counts.try_into().ok()?,
            empty_clouds,
            first_last_stamp: stamped.then_some((first, last)),
        })
    }
}

/// The progress of a killed instance: the last record of its journal lines (each line a record
/// written by [`Progress::encode`], in order). Returns it (`None` without a line) and how many
/// lines were read; the first line that is not a record ends the journal.
pub fn restored(lines: &[String]) -> (Option<Progress>, usize) {
    let mut last = None;
    let mut n = 0;
    for line in lines {
        let Some(p) = Progress::decode(line) else { break };
        last = Some(p);
        n += 1;
    }
    (last, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_last_record_is_the_progress_and_a_line_that_is_not_one_ends_the_journal() {
        let big = Progress {
            items: 123_456_789,
            counts: [1, 2, 3, 4, 5, u64::MAX, 6, 7],
            empty_clouds: 7,
            first_last_stamp: Some((10, u64::MAX)),
        };
        let small = Progress { items: 3, ..Default::default() };
        assert_eq!(Progress::decode(&big.encode()), Some(big));
        assert_eq!(restored(&[]), (None, 0));
        let lines = vec![small.encode(), big.encode(), "items=3".to_string(), small.encode()];
        assert_eq!(restored(&lines), (Some(big), 2));
        let six = "v1 items=3 counts=1,2,3,4,5,6 empty=0 first=0 last=0 stamped=0";
        assert_eq!(Progress::decode(six).map(|p| p.counts), Some([1, 2, 3, 4, 5, 6, 0, 0]));
    }
}
