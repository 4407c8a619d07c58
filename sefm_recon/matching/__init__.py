"""SeFM matching stages: rough (keypoint DP), dense (segment DP), validity."""
