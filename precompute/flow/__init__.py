"""The max-flow table builder: flow networks between level sets, exact max-flow, the 1-D closed form, build-size guidance."""
