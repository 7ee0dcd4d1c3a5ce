//! Frames decoded on a thread of their own, ahead of the tracking. Decoding a frame's two
//! images (PNG or JPEG) is single-threaded work of a few milliseconds; done on the tracking
//! thread it would sit between frames, while on a thread of its own it overlaps the parts of
//! the tracking that leave a core idle (the serial steps between the parallel passes).

use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::JoinHandle;
use std::time::Instant;

/// Frames `0..n` loaded in order on a reader thread, at most two ahead of the consumer.
pub(crate) struct ReadAhead<T> {
    /// `(index, loaded value, load time in ms)`; `None` once dropped.
    rx: Option<Receiver<(usize, T, f64)>>,
    thread: Option<JoinHandle<()>>,
}

impl<T: Send + 'static> ReadAhead<T> {
    /// Starts loading frames `0..n` with `load` on a thread named `rgbid-read`.
    pub(crate) fn spawn(
        n: usize,
        mut load: impl FnMut(usize) -> T + Send + 'static,
    ) -> std::io::Result<Self> {
        // One frame waits in the channel and the reader decodes the next one: two ahead.
        let (tx, rx) = sync_channel(1);
        let thread = std::thread::Builder::new()
            .name("rgbid-read".into())
            .spawn(move || {
                for i in 0..n {
                    let t0 = Instant::now();
                    let value = load(i);
                    let ms = t0.elapsed().as_secs_f64() * 1e3;
                    // The consumer has stopped (done, interrupted or failed).
                    if tx.send((i, value, ms)).is_err() {
                        break;
                    }
                }
            })?;
        Ok(Self {
            rx: Some(rx),
            thread: Some(thread),
        })
    }

    /// Frame `i` and its load time (ms). Frames before `i` that were not taken are dropped
    /// (the caller skipped them). An error when `i` is past the end or the reader thread
    /// stopped early (it panicked).
    pub(crate) fn get(&mut self, i: usize) -> anyhow::Result<(T, f64)> {
        let rx = self
            .rx
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("the frame reader was closed"))?;
        loop {
            match rx.recv() {
                Ok((j, value, ms)) if j == i => return Ok((value, ms)),
                Ok((j, _, _)) if j < i => continue,
                Ok((j, _, _)) => {
                    anyhow::bail!("the frame reader is at frame {j}, past the requested frame {i}")
                }
                Err(_) => anyhow::bail!("the frame reader thread stopped before frame {i}"),
            }
        }
    }
}

impl<T> Drop for ReadAhead<T> {
    fn drop(&mut self) {
        // Closing the channel first makes a reader blocked on a full channel return.
        drop(self.rx.take());
        if let Some(t) = self.thread.take() {
            // A panic of the reader was reported by `get` already.
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn read_ahead_delivers_frames_in_order_and_skips_on_request() {
        let mut r = ReadAhead::spawn(6, |i| i * 10).expect("thread");
        assert_eq!(r.get(0).expect("frame 0").0, 0);
        assert_eq!(r.get(1).expect("frame 1").0, 10);
        assert_eq!(r.get(4).expect("frame 4").0, 40);
        assert!(r.get(2).is_err(), "frames already passed are not delivered");
        let mut r = ReadAhead::spawn(2, |i| i).expect("thread");
        assert_eq!(r.get(1).expect("frame 1").0, 1);
        assert!(r.get(2).is_err(), "past the end");
    }

    #[test]
    fn read_ahead_reports_a_reader_that_stopped() {
        let mut r = ReadAhead::spawn(3, |i| {
            assert!(i < 1, "reader failure at frame {i}");
            i
        })
        .expect("thread");
        assert_eq!(r.get(0).expect("frame 0").0, 0);
        let e = r.get(1).expect_err("the reader panicked");
        assert!(e.to_string().contains("stopped before frame 1"), "{e}");
    }

    #[test]
    fn dropping_a_read_ahead_early_ends_its_thread() {
        let r = ReadAhead::spawn(1000, |i| vec![i; 1000]).expect("thread");
        drop(r);
    }
}
