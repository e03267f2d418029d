//! Which pixels of an image a process traces. Pixels are dealt to ranks in runs of
//! `SHARE_PIXELS` (about a row), round robin, so that every rank gets some of the image's middle,
//! where the medium is and paths are long. A pixel's random numbers depend on its index only, so
//! each pixel's value is the same whichever rank traces it.

/// Consecutive pixels dealt to one rank at a time.
pub const SHARE_PIXELS: u32 = 64;

/// The pixels (indices y·width + x) a pass traces.
#[derive(Debug, Clone, PartialEq)]
pub enum PixelSet {
    /// Every pixel of a `pixels`-pixel image.
    All(u32),
    /// Rank `rank`'s share of a `pixels`-pixel image split over `ranks`.
    Share { pixels: u32, rank: u32, ranks: u32 },
    /// The listed pixels (a pixel batch's), each traced once per listing.
    List(Vec<u32>),
}

impl PixelSet {
    /// Rank `rank`'s share of every pixel of a `pixels`-pixel image (all of it for one rank).
    pub fn share(pixels: u32, rank: usize, ranks: usize) -> PixelSet {
        if ranks <= 1 {
            PixelSet::All(pixels)
        } else {
            PixelSet::Share {
                pixels,
                rank: rank as u32,
                ranks: ranks as u32,
            }
        }
    }

    /// Rank `rank`'s share of a list: every `ranks`-th entry from the `rank`-th.
    pub fn share_of_list(list: &[u32], rank: usize, ranks: usize) -> PixelSet {
        PixelSet::List(
            list.iter()
                .skip(rank)
                .step_by(ranks.max(1))
                .copied()
                .collect(),
        )
    }

    /// How many pixels the set holds.
    pub fn len(&self) -> u64 {
        match self {
            PixelSet::All(pixels) => *pixels as u64,
            PixelSet::Share {
                pixels,
                rank,
                ranks,
            } => {
                let runs = pixels.div_ceil(SHARE_PIXELS);
                let mine = (runs + ranks - 1 - rank) / ranks;
                let mut n = mine as u64 * SHARE_PIXELS as u64;
                // The image's last run may be short, and it is this rank's if its index is.
                let last = runs.saturating_sub(1);
                if mine > 0 && last % ranks == *rank {
                    n -= (runs * SHARE_PIXELS - pixels) as u64;
                }
                n
            }
            PixelSet::List(list) => list.len() as u64,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The pixel index of the set's `i`-th pixel (`i < len()`).
    #[inline]
    pub fn pixel(&self, i: u64) -> u32 {
        match self {
            PixelSet::All(_) => i as u32,
            PixelSet::Share { rank, ranks, .. } => {
                let run = (i / SHARE_PIXELS as u64) as u32 * ranks + rank;
                run * SHARE_PIXELS + (i % SHARE_PIXELS as u64) as u32
            }
            PixelSet::List(list) => list[i as usize],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pixel belongs to exactly one rank's share, for image sizes around the run length.
    #[test]
    fn shares_cover_every_pixel_once() {
        for pixels in [0, 1, 63, 64, 65, 200, 4096, 4097] {
            for ranks in 1..=5 {
                let mut seen = vec![0u32; pixels as usize];
                for rank in 0..ranks {
                    let set = PixelSet::share(pixels, rank, ranks);
                    for i in 0..set.len() {
                        seen[set.pixel(i) as usize] += 1;
                    }
                }
                assert!(
                    seen.iter().all(|&n| n == 1),
                    "{pixels} pixels over {ranks} ranks: {seen:?}"
                );
            }
        }
    }

    #[test]
    fn list_shares_deal_entries_round_robin() {
        let list = [5, 9, 9, 2, 7];
        assert_eq!(
            PixelSet::share_of_list(&list, 1, 2),
            PixelSet::List(vec![9, 2])
        );
        assert_eq!(
            PixelSet::share_of_list(&list, 0, 2),
            PixelSet::List(vec![5, 9, 7])
        );
    }
}
