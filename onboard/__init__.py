"""The onboard agent: DEKF learning and tube LBMPC for one vehicle, plus its process runner."""
