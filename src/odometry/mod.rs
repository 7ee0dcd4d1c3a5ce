//! Dense RGB-D odometry (filled next).
